"""The e2e WireGuard side: mode, MTU, subnet, and the configs fleetctl's deploy code makes."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from fleetctl.e2e import wireguard
from fleetctl.errors import EnvironmentMissing, FleetError


def test_mode_follows_the_flag_and_the_tun_device(tmp_path: Path) -> None:
    tun = tmp_path / "tun"
    assert not wireguard.decide("auto", tun).on
    assert wireguard.decide("auto", tun).describe().startswith("off: ")
    assert f"{tun} is missing" in wireguard.decide("auto", tun).why
    with pytest.raises(EnvironmentMissing, match="--wireguard on"):
        wireguard.decide("on", tun)
    tun.touch()
    assert wireguard.decide("auto", tun).describe().startswith("on: ")
    assert wireguard.decide("on", tun).on
    assert wireguard.decide("off", tun).describe().startswith("off: --wireguard off")
    with pytest.raises(FleetError):
        wireguard.decide("maybe", tun)


def test_tunnel_mtu_leaves_room_for_the_encapsulation() -> None:
    assert wireguard.tunnel_mtu(1500) == 1420
    assert wireguard.tunnel_mtu(600) == 576


def test_the_vpn_subnet_avoids_the_run_networks() -> None:
    assert wireguard.choose_subnet(["172.18.0.0/16"]) == "10.8.0.0/24"
    assert wireguard.choose_subnet(["10.0.0.0/8"]) == "172.30.250.0/24"
    with pytest.raises(FleetError):
        wireguard.choose_subnet(["0.0.0.0/0"])


def test_configs_come_from_the_fleet_and_stay_secret(tmp_path: Path) -> None:
    tunnel = wireguard.Tunnel(tmp_path, "ab12", 1420)
    tunnel.create(["10.8.0.0/16"])  # forces the second candidate subnet
    assert tunnel.server_vpn_ip == "10.88.0.1" and tunnel.robot_vpn_ip == "10.88.0.2"
    server = tunnel.conf_dir / "fs-ab12.conf"
    text = server.read_text()
    assert "MTU = 1420" in text and "ListenPort = 51820" in text
    assert "AllowedIPs = 10.88.0.2/32" in text
    with pytest.raises(FleetError, match="endpoint"):
        tunnel.robot_iface()
    tunnel.set_endpoint("172.19.0.3")
    iface = tunnel.robot_iface()
    assert iface == "fr-ab12-1" and tunnel.robot_iface() == "fr-ab12-2"
    assert len(iface) <= 15  # Linux interface names
    robot = (tunnel.conf_dir / f"{iface}.conf").read_text()
    assert "Endpoint = 172.19.0.3:51820" in robot and "MTU = 1420" in robot
    assert "Address = 10.88.0.2/32" in robot
    for path in (server, tunnel.conf_dir / f"{iface}.conf"):
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(tunnel.conf_dir.stat().st_mode) == 0o700
    assert tunnel.container_env(iface)["WG_CONFIG"] == f"/e2e/wg/{iface}.conf"
    assert tunnel.server_url(8080) == "ws://10.88.0.1:8080/"
