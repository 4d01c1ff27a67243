"""The images' entrypoint (images/entrypoint.sh, this checkout's) bringing WireGuard up.

It runs in the base image the fleetctl images are built on (wireguard-go, wg, wg-quick,
iproute2), as root with NET_ADMIN and /dev/net/tun as `fleetctl up` runs the server, on a
fleet's real server wg0.conf, with WG_REQUIRED=1 as `up` sets it.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from fleetctl.deploy import operations as ops
from fleetctl.deploy.dockercli import image_exists, subprocess_runner
from tests.deploy.conftest import SeededKeySource

pytestmark = [pytest.mark.docker,
              pytest.mark.skipif(shutil.which("docker") is None, reason="needs docker")]

BASE_IMAGE = "fleetctl/base:bookworm"
ENTRYPOINT = Path(__file__).resolve().parents[2] / "images" / "entrypoint.sh"


def _run_entrypoint(conf: Path) -> subprocess.CompletedProcess[str]:
    if not image_exists(subprocess_runner, BASE_IMAGE):
        pytest.skip(f"image {BASE_IMAGE} missing (run 'fleetctl build')")
    if not Path("/dev/net/tun").exists():
        pytest.skip("needs /dev/net/tun for wireguard-go")
    return subprocess.run(
        ["docker", "run", "--rm", "--user", "root", "--cap-add", "NET_ADMIN",
         "--device", "/dev/net/tun:/dev/net/tun",
         "-v", f"{ENTRYPOINT}:/usr/local/bin/fleetctl-entrypoint:ro",
         "-v", f"{conf.parent}:/etc/fleetctl/wg:ro",
         "-e", "WG_CONFIG=/etc/fleetctl/wg/wg0.conf", "-e", "WG_REQUIRED=1",
         "--entrypoint", "/usr/local/bin/fleetctl-entrypoint", BASE_IMAGE,
         "wg", "show", "wg0", "peers"],
        capture_output=True, text=True, timeout=120, check=False)


@pytest.fixture
def server_conf(tmp_path: Path) -> Path:
    fleet = tmp_path / "fleet"
    keys = SeededKeySource()
    ops.create_fleet(fleet, endpoint="fleet.example:51820", keys=keys)
    ops.add_robot(fleet, "husky1", keys=keys)
    return fleet / "server" / "wireguard" / "wg0.conf"


def test_the_tunnel_comes_up_with_the_fleets_peers(server_conf: Path) -> None:
    res = _run_entrypoint(server_conf)
    assert res.returncode == 0, res.stderr
    assert "fleetctl-entrypoint: WireGuard wg0 up: wg0" in res.stderr
    assert len(res.stdout.split()) == 1  # husky1, the one peer


def test_a_config_wg_refuses_is_fatal_with_wg_required(server_conf: Path) -> None:
    """A peer's key mistyped in a hand edit: wg refused the config, the entrypoint said
    "WireGuard wg0 up" and the server ran, healthy, with no peer at all (the function ran
    as an `if` condition, where bash ignores `set -e`)."""
    text = server_conf.read_text()
    key_line = next(line for line in text.splitlines() if line.startswith("PublicKey = "))
    server_conf.write_text(text.replace(key_line, "PublicKey = notakey"))
    res = _run_entrypoint(server_conf)
    assert res.returncode == 78, res.stderr
    assert "Key is not the correct length or format: `notakey'" in res.stderr
    assert "wg0.conf: wg setconf refused it" in res.stderr
    assert "WG_REQUIRED=1: giving up" in res.stderr
    assert "WireGuard wg0 up" not in res.stderr
