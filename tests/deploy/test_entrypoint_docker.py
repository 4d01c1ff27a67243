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


# Run in the container: hold UDP port 51820 (the fleet's ListenPort) in the container's
# network namespace for argv[1] seconds, while the entrypoint brings the tunnel up.
_HOLD_THE_PORT = """
import socket, subprocess, sys, threading
held = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
held.bind(("0.0.0.0", 51820))
release = threading.Timer(float(sys.argv[1]), held.close)
release.daemon = True  # the container ends with the entrypoint
release.start()
sys.exit(subprocess.run(["/usr/local/bin/fleetctl-entrypoint", *sys.argv[2:]]).returncode)
"""


def _run_entrypoint(conf: Path, *, hold_port_s: float | None = None,
                    command: tuple[str, ...] = ("wg", "show", "wg0", "peers"),
                    ) -> subprocess.CompletedProcess[str]:
    if not image_exists(subprocess_runner, BASE_IMAGE):
        pytest.skip(f"image {BASE_IMAGE} missing (run 'fleetctl build')")
    if not Path("/dev/net/tun").exists():
        pytest.skip("needs /dev/net/tun for wireguard-go")
    start = (["/usr/local/bin/fleetctl-entrypoint"] if hold_port_s is None
             else ["python3", "-c", _HOLD_THE_PORT, str(hold_port_s)])
    return subprocess.run(
        ["docker", "run", "--rm", "--user", "root", "--cap-add", "NET_ADMIN",
         "--device", "/dev/net/tun:/dev/net/tun",
         "-v", f"{ENTRYPOINT}:/usr/local/bin/fleetctl-entrypoint:ro",
         "-v", f"{conf.parent}:/etc/fleetctl/wg:ro",
         "-e", "WG_CONFIG=/etc/fleetctl/wg/wg0.conf", "-e", "WG_REQUIRED=1",
         "--entrypoint", start[0], BASE_IMAGE, *start[1:], *command],
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


def test_a_listen_port_taken_for_a_moment_is_waited_out(server_conf: Path) -> None:
    """Once in 15 e2e fleet starts the server stopped at wg setconf with "Address already
    in use" (WG_REQUIRED=1: exit 78). A holder that lets go within 3 s no longer stops
    it, and the log names the holder."""
    res = _run_entrypoint(server_conf, hold_port_s=1.0,
                          command=("wg", "show", "wg0", "listen-port"))
    assert res.returncode == 0, res.stderr
    assert "UDP port 51820 is taken in this network namespace by:" in res.stderr
    assert '"python3"' in res.stderr  # ss names the process
    assert "wg setconf applied on the second attempt" in res.stderr
    assert "fleetctl-entrypoint: WireGuard wg0 up: wg0" in res.stderr
    assert res.stdout.strip() == "51820"


def test_a_listen_port_kept_taken_is_fatal_and_names_the_holder(server_conf: Path) -> None:
    res = _run_entrypoint(server_conf, hold_port_s=60.0)
    assert res.returncode == 78, res.stderr
    assert "UDP port 51820 is taken in this network namespace by:" in res.stderr
    assert '"python3"' in res.stderr
    assert "wg0.conf: wg setconf refused it" in res.stderr
    assert "WireGuard wg0 up" not in res.stderr
