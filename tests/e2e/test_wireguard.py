"""The e2e WireGuard choices: mode, MTU, subnet (the configs: tests/e2e/test_deployment.py)."""

from __future__ import annotations

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
