"""Rendering the compose deployment of a real fleet directory (made by `fleetctl init`)."""

from __future__ import annotations

import shutil
import stat
import subprocess
from pathlib import Path

import pytest
import yaml

from fleetctl.cli.main import main
from fleetctl.deploy import compose
from fleetctl.errors import ConfigError, EnvironmentMissing, FleetError


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    fleet_dir = tmp_path / "yard"
    assert main(["init", str(fleet_dir), "--endpoint", "fleet.example:51820"]) == 0
    for name, ip in (("husky1", "10.8.0.2"), ("jackal2", "10.8.0.3")):
        assert main(["add-robot", name, "--ip", ip, "--fleet", str(fleet_dir)]) == 0
    return fleet_dir


def test_plan_reads_robots_and_addresses(fleet: Path) -> None:
    plan = compose.plan_for(fleet, wireguard="off")
    assert [(r.name, r.fleet_ip) for r in plan.robots] == [
        ("husky1", "10.8.0.2"), ("jackal2", "10.8.0.3")]
    assert (plan.server_ip, plan.fleet_subnet, plan.server_port) == (
        "10.8.0.1", "10.8.0.0/24", 8080)
    assert plan.project == "fleetctlyard"


def test_plain_mode_puts_robots_on_their_fleet_ips(fleet: Path) -> None:
    doc = compose.render(compose.plan_for(fleet, wireguard="off"))
    assert doc["version"] == "2.4"
    assert set(doc["services"]) == {"server", "webviz", "robot-husky1", "robot-jackal2"}
    robot = doc["services"]["robot-husky1"]
    assert robot["networks"]["fleet"] == {"ipv4_address": "10.8.0.2"}
    assert doc["services"]["server"]["networks"]["fleet"] == {"ipv4_address": "10.8.0.1"}
    ipam = doc["networks"]["fleet"]["ipam"]["config"][0]
    assert ipam == {"subnet": "10.8.0.0/24", "gateway": "10.8.0.254"}
    assert "cap_add" not in robot and "WG_CONFIG" not in robot["environment"]
    assert robot["depends_on"] == {"server": {"condition": "service_healthy"}}
    assert doc["services"]["webviz"]["ports"] == ["127.0.0.1:8000:8000"]


def test_wireguard_mode_runs_wireguard_go_with_endpoint_rewritten(fleet: Path) -> None:
    plan = compose.plan_for(fleet, wireguard="auto")
    if not plan.wireguard:
        pytest.skip("no /dev/net/tun on this host")
    doc = compose.render(plan)
    robot = doc["services"]["robot-husky1"]
    assert robot["cap_add"] == ["NET_ADMIN"] and robot["user"] == "root"
    assert robot["environment"]["WG_CONFIG"] == "/etc/fleetctl/wg/wg0.conf"
    assert doc["services"]["server"]["environment"]["WG_REQUIRED"] == "1"
    compose.write_files(plan)
    conf = plan.compose_dir / "robots" / "husky1" / "wg0.conf"
    assert "Endpoint = server:51820" in conf.read_text()
    assert stat.S_IMODE(conf.stat().st_mode) == 0o600
    assert stat.S_IMODE(plan.compose_dir.stat().st_mode) == 0o700


def test_written_server_config_uses_container_paths(fleet: Path) -> None:
    plan = compose.plan_for(fleet, wireguard="off")
    path = compose.write_files(plan)
    server = yaml.safe_load((plan.compose_dir / "server" / "server.yaml").read_text())
    assert server["database"] == "/var/lib/fleetctl/fleet.db"
    assert server["auth_map"] == "/etc/fleetctl/server/auth.yaml"
    assert (plan.compose_dir / "server" / "auth.yaml").is_file()
    assert yaml.safe_load(path.read_text()) == compose.render(plan)


@pytest.mark.skipif(shutil.which("docker-compose") is None, reason="needs docker-compose")
def test_compose_v1_accepts_the_file(fleet: Path) -> None:
    path = compose.write_files(compose.plan_for(fleet, wireguard="off"))
    res = subprocess.run(["docker-compose", "-f", str(path), "config", "-q"],
                         capture_output=True, text=True, check=False)
    assert res.returncode == 0, res.stderr


def test_bad_fleet_dirs_are_named(tmp_path: Path, fleet: Path) -> None:
    with pytest.raises(ConfigError, match=r"fleet\.yaml: missing"):
        compose.plan_for(tmp_path)
    (fleet / "robots" / "husky1" / "wireguard" / "wg0.conf").write_text("[Interface]\n")
    with pytest.raises(ConfigError, match=r"wg0.conf: field Address: missing"):
        compose.plan_for(fleet, wireguard="off")
    with pytest.raises(FleetError, match="run `fleetctl up"):
        compose.existing(tmp_path)


def test_wireguard_mode_choice(tmp_path: Path) -> None:
    absent = tmp_path / "tun"
    assert compose.wireguard_mode("off", absent)[0] is False
    on, note = compose.wireguard_mode("auto", absent)
    assert on is False and note.startswith("WARNING: WireGuard NOT used")
    with pytest.raises(EnvironmentMissing):
        compose.wireguard_mode("on", absent)
    absent.write_text("")
    assert compose.wireguard_mode("auto", absent)[0] is True
    with pytest.raises(FleetError, match="auto, on or off"):
        compose.wireguard_mode("maybe", absent)
