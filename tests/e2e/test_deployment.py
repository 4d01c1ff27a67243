"""The e2e fleet is `fleetctl up`'s: its files, its server service, e2e's few changes."""

from __future__ import annotations

import stat
from collections.abc import Sequence
from pathlib import Path

import pytest
import yaml

from fleetctl.deploy import compose
from fleetctl.deploy.dockercli import Completed
from fleetctl.deploy.dockerrun import run_args
from fleetctl.deploy.images import image_tag
from fleetctl.e2e.deployment import ROBOT_WG_DIR, SITE_PACKAGE, Deployment
from fleetctl.e2e.fleetrun import FleetRun
from fleetctl.e2e.topology import SERVER_SIDE, Topology
from fleetctl.tokens import hash_token

ROBOT_NET = "172.18.0.0/16"
NETS = [ROBOT_NET, "172.19.0.0/16"]


def _made(tmp_path: Path, wireguard: bool, source: Path | None = None) -> Deployment:
    deployment = Deployment(tmp_path / "raw", "ab12", wireguard, 1420, source)
    deployment.create(NETS, ROBOT_NET)
    return deployment


def test_the_server_is_ups_service_minus_ports_restart_and_address(tmp_path: Path) -> None:
    deployment = _made(tmp_path, True)
    ups = compose.server_service(deployment.plan)
    ours = deployment.server_service()
    assert set(ups) - set(ours) == {"ports"}
    assert ours["restart"] == "no" and ours["networks"] == ["fleet"]
    for key in ("image", "command", "user", "volumes", "environment", "cap_add", "devices"):
        assert ours[key] == ups[key], key
    assert ours["environment"]["WG_CONFIG"] == compose.SERVER_WG_CONF
    # What up wrote is what the container reads: the plain listener only in the tunnel.
    run_cfg = yaml.safe_load((deployment.plan.compose_dir / "server" / "server.yaml").read_text())
    assert run_cfg == compose.container_server_config(deployment.plan)
    assert run_cfg["listen_host"] == [deployment.plan.server_ip, "127.0.0.1"]
    key_file = deployment.plan.compose_dir / "secrets" / "tls.key"
    assert stat.S_IMODE(key_file.stat().st_mode) == 0o600


def test_the_consumers_are_a_viewer_of_the_fleet(tmp_path: Path) -> None:
    deployment = _made(tmp_path, True)
    auth = yaml.safe_load((deployment.fleet_dir / "server" / "auth.yaml").read_text())
    (viewer,) = [i for i in auth["identities"] if "token_sha256" in i]
    assert viewer["token_sha256"] == hash_token(deployment.token)
    assert all(r["op"] == "receive" for r in viewer["rules"])
    assert (deployment.work / "token").read_text() == deployment.token
    assert (deployment.work / "tls-cert.pem").read_text() == deployment.plan.tls_cert.read_text()
    assert deployment.consumer_url("172.19.0.3") == "wss://172.19.0.3:8443/"
    assert deployment.token not in repr(deployment)


def test_robots_use_ups_robot_config_and_reach_server_by_name(tmp_path: Path) -> None:
    deployment = _made(tmp_path, True)
    conf = deployment.robot_wg_dir / "wg0.conf"
    assert "Endpoint = server:51820" in conf.read_text() and "MTU = 1420" in conf.read_text()
    assert stat.S_IMODE(conf.stat().st_mode) == 0o600
    assert stat.S_IMODE(conf.parent.stat().st_mode) == 0o700
    options = deployment.robot_options("172.19.0.3")
    assert options["hosts"] == {"server": "172.19.0.3"}
    assert options["env"] == {"WG_CONFIG": f"{ROBOT_WG_DIR}/wg0.conf", "WG_REQUIRED": "1"}
    assert options["mounts"] == [f"{deployment.robot_wg_dir}:{ROBOT_WG_DIR}:ro"]
    assert deployment.robot_url("172.19.0.3") == f"ws://{deployment.plan.server_ip}:8080/"
    assert deployment.robot_vpn_ip == "10.8.0.2"
    # A consumer in the server's namespace (the peer scenarios) reaches the plain
    # listener on loopback, which up binds beside the tunnel address.
    assert deployment.loopback_url() == "ws://127.0.0.1:8080/"
    cfg = yaml.safe_load((deployment.plan.compose_dir / "server" / "server.yaml").read_text())
    assert "127.0.0.1" in cfg["listen_host"]


def test_routed_robots_are_named_by_their_network(tmp_path: Path) -> None:
    deployment = _made(tmp_path, False, source=tmp_path / "checkout")
    assert deployment.robot_options("172.19.0.3") == {}
    assert deployment.robot_url("172.19.0.3") == "ws://172.19.0.3:8080/"
    run_dir = deployment.plan.compose_dir / "server"
    cfg = yaml.safe_load((run_dir / "server.yaml").read_text())
    assert cfg["listen_host"] == "0.0.0.0"
    assert cfg["auth_map"] == f"{compose.RUN_ETC}/e2e-auth.yaml"
    fleet_auth = yaml.safe_load((deployment.fleet_dir / "server" / "auth.yaml").read_text())
    ours = yaml.safe_load((run_dir / "e2e-auth.yaml").read_text())
    robot = ours["identities"][0]
    assert robot["cidr"] == ROBOT_NET and "ip" not in robot
    assert ours["identities"][1:] == fleet_auth["identities"][1:]
    service = deployment.server_service()
    assert service["volumes"][-1] == f"{tmp_path / 'checkout' / 'fleetctl'}:{SITE_PACKAGE}:ro"
    assert "devices" not in service


def test_the_topology_starts_the_service_with_the_runs_labels(tmp_path: Path) -> None:
    deployment = _made(tmp_path, True)
    calls: list[list[str]] = []

    def docker(argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        args = list(argv)
        calls.append(args)
        out = ('[{"NetworkSettings": {"Networks": {"fce2e-ab12-server": '
               '{"IPAddress": "172.19.0.3"}}}}]' if args[1] == "inspect" else "")
        return Completed(tuple(args), 0, out, "")

    topo = Topology("ab12", docker, owner="host:1:2")
    topo.networks[SERVER_SIDE] = "fce2e-ab12-server"
    topo.subnets.update({"robot": NETS[0], SERVER_SIDE: NETS[1]})
    topo.router_ips[SERVER_SIDE] = "172.19.0.2"
    server = topo.start_service("server", SERVER_SIDE, deployment.server_service(),
                                {"server-data": None})
    assert server.ip == "172.19.0.3" and server.name == "fce2e-ab12-server"
    expected = run_args(deployment.server_service(), name=server.name,
                        networks={"fleet": "fce2e-ab12-server"}, volumes={"server-data": None},
                        extra=[*topo.labels, "--network-alias", "server",
                               "--cap-add", "NET_ADMIN"])
    assert calls[0] == ["docker", "run", *expected]
    assert "--publish" not in calls[0]


@pytest.mark.parametrize("wireguard", [True, False])
def test_create_twice_starts_from_a_fresh_fleet(tmp_path: Path, wireguard: bool) -> None:
    first = _made(tmp_path, wireguard)
    token = first.token
    again = _made(tmp_path, wireguard)
    assert again.token != token


def test_images_are_pinned_by_id_for_the_whole_run(tmp_path: Path) -> None:
    def docker(argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        ids = {"fleetctl/server": "sha256:aaa", "fleetctl/client": "sha256:bbb"}
        image = argv[-1].split(":")[0]
        return Completed(tuple(argv), 0 if image in ids else 1, ids.get(image, ""), "")

    fleet = FleetRun(Topology("ab12", docker, owner="h:1:2"), tmp_path, _made(tmp_path, True))
    assert fleet.image("server") == image_tag("server")  # before pinning: the tag
    fleet.pin_images("server", "client", "webviz")
    assert fleet.image("server") == "sha256:aaa" and fleet.image("client") == "sha256:bbb"
    assert fleet.image("webviz") == image_tag("webviz")  # not resolvable: stays a tag
