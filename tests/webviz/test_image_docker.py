"""The webviz image run as docs/webviz.md says, for a fleet with its own message types:
the fleet's ``msg_types/`` mounted read-only and ``--fleet`` (the image's command without
them serves the standard types only, and the page showed nothing of a robot's own type)."""

from __future__ import annotations

import json
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetctl.deploy.dockercli import image_exists, subprocess_runner
from fleetctl.deploy.images import image_tag
from fleetctl.deploy.msgtypes import load_msg_types
from fleetctl.waiting import wait_until
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.schema import describe
from tests.webviz.test_cli import ARM_MSG, STATUS_MSG, get, write_fleet_types

pytestmark = [
    pytest.mark.docker,
    pytest.mark.skipif(shutil.which("docker") is None, reason="needs docker"),
]

STATUS = "types/my_robot_msgs/msg/Status.json"
START_TIMEOUT_S = 30


def run_image(*args: str) -> Iterator[str]:
    """``docker run -d`` of the webviz image with *args* (before the image: mounts; after:
    the command); yields the page's URL on loopback and removes the container."""
    image = image_tag("webviz")
    if not image_exists(subprocess_runner, image):
        pytest.fail(f"{image} missing: run `fleetctl build` first")
    split = args.index("--")
    cid = subprocess.run(
        ["docker", "run", "-d", "-p", "127.0.0.1::8000", *args[:split], image, *args[split + 1:]],
        capture_output=True, text=True, check=True, timeout=60).stdout.strip()
    try:
        port = subprocess.run(["docker", "port", cid, "8000/tcp"], capture_output=True,
                              text=True, check=True, timeout=30).stdout.split(":")[-1].strip()
        url = f"http://127.0.0.1:{port}/"

        def listening() -> bool:
            state = subprocess.run(["docker", "inspect", "-f", "{{.State.Running}}", cid],
                                   capture_output=True, text=True, timeout=30).stdout
            if state.strip() != "true":  # it stopped: say why, no use waiting
                logs = subprocess.run(["docker", "logs", cid], capture_output=True,
                                      text=True, timeout=30)
                pytest.fail(f"the webviz container stopped: {logs.stdout}{logs.stderr}")
            return _answer(url) is not None

        wait_until(listening, START_TIMEOUT_S, poll_s=0.2, describe=f"{image} at {url}")
        yield url
    finally:
        subprocess.run(["docker", "rm", "-f", cid], capture_output=True, timeout=60)


def _answer(url: str) -> int | None:
    try:
        return get(url + "config.json")[0]
    except OSError:  # not listening yet (refused, reset while the port is published)
        return None


def test_the_image_serves_the_fleets_own_types_when_run_as_documented(tmp_path: Path) -> None:
    fleet = write_fleet_types(tmp_path / "fleet", {"my_robot_msgs/msg/Status.msg": STATUS_MSG,
                                                   "my_robot_msgs/msg/Arm.msg": ARM_MSG})
    for path in (fleet / "msg_types").rglob("*"):  # the image runs as uid 10001
        path.chmod(0o755 if path.is_dir() else 0o644)
    (fleet / "msg_types").chmod(0o755)
    command = ["fleetctl", "webviz", "--host", "0.0.0.0", "--port", "8000",
               "--server-url", "wss://fleet.example.org:8443/"]
    # The image's own command: the standard types only.
    for url in run_image("--", *command):
        code, body = get(url + STATUS)
        assert code == 404 and b"my_robot_msgs/msg/Status" in body
    # docs/webviz.md's docker run: the fleet's msg_types read-only, and --fleet.
    for url in run_image("-v", f"{fleet / 'msg_types'}:/fleet/msg_types:ro",
                         "--", *command, "--fleet", "/fleet"):
        code, body = get(url + STATUS)
        assert code == 200, body
        assert json.loads(body) == describe(
            TypeRegistry.default_with(load_msg_types(fleet).texts), "my_robot_msgs/msg/Status")
        assert get(url + "config.json") == (
            200, b'{"server_url": "wss://fleet.example.org:8443/"}')
