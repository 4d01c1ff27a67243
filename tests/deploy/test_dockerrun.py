"""Compose services as ``docker run`` arguments: every key ``up`` renders, nothing dropped."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from fleetctl.deploy import compose, operations
from fleetctl.deploy.dockerrun import run_args
from fleetctl.errors import FleetError


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    fleet_dir = tmp_path / "fleet"
    operations.create_fleet(fleet_dir, endpoint="vpn.example.org:51820")
    operations.add_robot(fleet_dir, "husky1")
    return fleet_dir


def _pairs(argv: list[str], flag: str) -> list[str]:
    return [argv[i + 1] for i, a in enumerate(argv) if a == flag]


def test_the_server_service_up_renders_converts_whole(fleet: Path) -> None:
    plan = compose.plan_for(fleet, compose.Options("p", wireguard="on"))
    service = compose.server_service(plan)
    assert service == compose.render(plan)["services"]["server"]
    argv = run_args(service, name="srv", networks={"fleet": "e2e-net"},
                    volumes={"server-data": "srv-data"}, extra=["--label", "x=1"])
    assert argv[:3] == ["--detach", "--name", "srv"]
    # Image and command last, as the compose file has them.
    tail = [service["image"], *service["command"]]
    assert argv[-len(tail):] == tail
    assert argv[-len(tail) - 2:-len(tail)] == ["--label", "x=1"]
    assert _pairs(argv, "--user") == ["root"]
    assert _pairs(argv, "--restart") == ["unless-stopped"]
    assert _pairs(argv, "--cap-add") == ["NET_ADMIN"]
    assert _pairs(argv, "--device") == ["/dev/net/tun:/dev/net/tun"]
    assert _pairs(argv, "--network") == ["e2e-net"]
    assert _pairs(argv, "--publish") == service["ports"]
    env = _pairs(argv, "--env")
    assert f"WG_CONFIG={compose.SERVER_WG_CONF}" in env and "WG_REQUIRED=1" in env
    assert f"FLEETCTL_SECRETS={compose.SECRETS_ETC}" in env
    volumes = _pairs(argv, "--volume")
    assert f"{fleet.resolve() / 'server'}:{compose.FLEET_ETC}:ro" in volumes
    assert "srv-data:/var/lib/fleetctl" in volumes


def test_plain_mode_keeps_the_static_address_and_anonymous_volumes(fleet: Path) -> None:
    plan = compose.plan_for(fleet, compose.Options("p", wireguard="off"))
    argv = run_args(compose.server_service(plan), name="srv", networks={"fleet": "n"},
                    volumes={"server-data": None})
    assert _pairs(argv, "--ip") == [plan.server_ip]
    assert "/var/lib/fleetctl" in _pairs(argv, "--volume")
    assert "--device" not in argv


def _service(**extra: Any) -> dict[str, Any]:
    return {"image": "img:1", "networks": ["fleet"], **extra}


def test_environment_lists_labels_hosts_and_aliases() -> None:
    service = _service(environment={"A": 1, "B": None, "C": True}, labels={"k": "v"},
                       extra_hosts=["server:10.0.0.3"], networks={"fleet": {"aliases": ["srv"]}})
    argv = run_args(service, name="c", networks={"fleet": "n"})
    assert _pairs(argv, "--env") == ["A=1", "B", "C=true"]
    assert _pairs(argv, "--label") == ["k=v"]
    assert _pairs(argv, "--add-host") == ["server:10.0.0.3"]
    assert _pairs(argv, "--network-alias") == ["srv"]
    assert argv[-1] == "img:1"
    listed = run_args(_service(environment=["A=1", "B"]), name="c", networks={"fleet": "n"})
    assert _pairs(listed, "--env") == ["A=1", "B"]


@pytest.mark.parametrize(("service", "match"), [
    (_service(depends_on={"server": {"condition": "service_healthy"}}), "depends_on"),
    (_service(healthcheck={"test": ["CMD", "true"]}), "healthcheck"),
    (_service(command="fleetctl server"), "list of arguments"),
    ({"networks": ["fleet"]}, "no image"),
    (_service(networks=["fleet", "other"]), "exactly one network"),
    (_service(networks=["elsewhere"]), "not mapped"),
    (_service(volumes=["data:/var/lib/x"]), "named volume 'data'"),
    (_service(networks={"fleet": {"priority": 3}}), "unsupported"),
])
def test_what_docker_run_cannot_say_is_refused(service: dict[str, Any], match: str) -> None:
    with pytest.raises(FleetError, match=match):
        run_args(service, name="c", networks={"fleet": "n"})


def test_bind_mounts_pass_through_and_named_volumes_need_a_mapping() -> None:
    svc = _service(volumes=["/host:/ctr:ro", "./rel:/r", "data:/d:ro"])
    argv = run_args(svc, name="c", networks={"fleet": "n"}, volumes={"data": "vol1"})
    assert _pairs(argv, "--volume") == ["/host:/ctr:ro", "./rel:/r", "vol1:/d:ro"]
    with pytest.raises(FleetError, match="named volume"):
        run_args(svc, name="c", networks={"fleet": "n"}, volumes={})
