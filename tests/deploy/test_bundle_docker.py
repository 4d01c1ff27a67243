"""The robot bundle's README, followed as written, in a container playing the robot.

The robot is a container of the plain Debian base image (``fleetctl/base:bookworm``: Python,
WireGuard tools and wireguard-go, no fleetctl, no ROS) with NET_ADMIN and ``/dev/net/tun``.
The bundle is copied in and the README's marked blocks run verbatim, in order: the tunnel
without systemd (``wg-quick`` falls back to wireguard-go: no kernel WireGuard here), the
venv, the ROS 2 wheels (the x86_64 route without ROS from apt), the client's files, and the
client in the foreground. pip reads the wheelhouses of ``fleetctl build`` (mounted, through
``PIP_NO_INDEX``/``PIP_FIND_LINKS``: the robot's pip would read PyPI). The operator is root
here and ``sudo`` a pass-through; systemd, apt and ROS from apt are what a container cannot
play (their blocks are checked for syntax in test_bundle.py).

The server is a ``fleetctl/server`` container with the fleet's configs, its WireGuard up by
the image's entrypoint, on a network this test creates; the bundle's ``Endpoint`` names it.
Pass: the robot is online in the server's ``/robots`` within 30 s of starting the client,
having reached the server's tunnel address (its identity is its WireGuard address).
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

from fleetctl.deploy import operations as ops
from fleetctl.deploy.export import export_robot
from fleetctl.waiting import wait_until
from tests.deploy.conftest import SeededKeySource
from tests.deploy.test_bundle import readme_blocks

pytestmark = [pytest.mark.docker, pytest.mark.slow]

os.environ.setdefault("TESTCONTAINERS_RYUK_DISABLED", "true")  # Ryuk cannot be pulled here

SERVER_IMAGE = "fleetctl/server:0.1.0"
ROBOT_IMAGE = "fleetctl/base:bookworm"
WHEELS = Path(__file__).resolve().parents[2] / "build" / "docker" / "wheels"
ROBOT = "husky1"
BUNDLE = f"/root/{ROBOT}-bundle"  # where the operator copied the bundle
SERVER_ETC = "/etc/fleetctl/server"
# The README's blocks a container can play, in the README's order.
ROBOT_BLOCKS = ("tunnel-config", "tunnel-quick", "tunnel-check", "venv", "ros-wheels",
                "install-files")
# Updating the robot to a new export, without systemd: the new wg0.conf in place
# (tunnel-config's line), then the README's update blocks a container can play.
UPDATE_BLOCKS = ("tunnel-config", "update-tunnel-quick", "update-venv", "update-files")
ONLINE_DEADLINE_S = 30.0


def _docker() -> Any:
    if shutil.which("docker") is None:
        pytest.skip("needs docker")
    try:
        import docker  # type: ignore[import-untyped]

        client = docker.from_env()
        client.ping()
    except Exception as exc:  # any failure to reach the engine means: no Docker here
        pytest.skip(f"no Docker engine: {exc}")
    for image in (SERVER_IMAGE, ROBOT_IMAGE):
        try:
            client.images.get(image)
        except docker.errors.ImageNotFound:
            pytest.skip(f"image {image} missing (run 'fleetctl build')")
    if not os.path.exists("/dev/net/tun"):
        pytest.skip("needs /dev/net/tun for wireguard-go")
    for house in ("base", "ros"):
        if not any((WHEELS / house).glob("*.whl")):
            pytest.skip(f"wheelhouse {WHEELS / house} is empty (run 'fleetctl build')")
    return client


@dataclass
class Deployment:
    server: Any  # testcontainers DockerContainer
    robot: Any
    bundle: Path
    fleet_dir: Path


def _server_config(fleet_dir: Path, out: Path) -> None:
    """The fleet's server configs for the container (as compose.py adapts them)."""
    out.mkdir(mode=0o755)
    cfg = yaml.safe_load((fleet_dir / "server" / "server.yaml").read_text())
    cfg.update(listen_host="0.0.0.0", database="/var/lib/fleetctl/fleet.db",
               auth_map=f"{SERVER_ETC}/auth.yaml")
    cfg.pop("web", None)  # only the relay is needed: no web page, no TLS files to copy
    (out / "server.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    shutil.copyfile(fleet_dir / "server" / "auth.yaml", out / "auth.yaml")
    shutil.copyfile(fleet_dir / "server" / "wireguard" / "wg0.conf", out / "wg0.conf")
    for path in out.iterdir():
        path.chmod(0o600 if path.name == "wg0.conf" else 0o644)


def _exec(container: Any, script: str, *, workdir: str = "/") -> str:
    """Run *script* with bash -e in *container*; fail the test with its output if it fails."""
    code, output = container.get_wrapped_container().exec_run(
        ["bash", "-e", "-c", script], workdir=workdir, user="root")
    text = output.decode("utf-8", "replace")
    assert code == 0, f"exit {code} from:\n{script}\n--- output ---\n{text[-4000:]}"
    return text


def _robots(server: Any) -> list[dict[str, Any]]:
    """The server's /robots, asked over loopback inside its container (no token needed)."""
    code, output = server.get_wrapped_container().exec_run(
        ["python3", "-c", "import urllib.request as u;"
         "print(u.urlopen('http://127.0.0.1:8080/robots', timeout=2).read().decode())"])
    if code != 0:
        return []
    doc = json.loads(output)
    return list(doc["robots"] if isinstance(doc, dict) else doc)


def _logs(container: Any) -> str:
    out, err = container.get_logs()
    return (out + err).decode("utf-8", "replace")[-4000:]


@pytest.fixture
def deployment(tmp_path: Path) -> Iterator[Deployment]:
    client = _docker()
    from testcontainers.core.container import DockerContainer
    from testcontainers.core.network import Network

    suffix = uuid.uuid4().hex[:8]
    server_name = f"fleetctl-bundle-server-{suffix}"
    fleet_dir = tmp_path / "fleet"
    # The Endpoint the bundle carries: the server container, by name on the test's network.
    keys = SeededKeySource()  # one source: the server's and the robot's keys must differ
    ops.create_fleet(fleet_dir, endpoint=f"{server_name}:51820", name="bundle-test",
                     keys=keys)
    ops.add_robot(fleet_dir, ROBOT, keys=keys)
    bundle = export_robot(fleet_dir, ROBOT, tmp_path / f"{ROBOT}-bundle").path  # real wheel
    _server_config(fleet_dir, tmp_path / "server")

    network = Network()
    network.create()
    started: list[Any] = []
    try:
        server = (DockerContainer(SERVER_IMAGE)
                  .with_name(server_name).with_network(network)
                  .with_env("WG_CONFIG", f"{SERVER_ETC}/wg0.conf").with_env("WG_REQUIRED", "1")
                  .with_volume_mapping(str(tmp_path / "server"), SERVER_ETC, "ro")
                  .with_kwargs(user="root", cap_add=["NET_ADMIN"],
                               devices=["/dev/net/tun:/dev/net/tun"]))
        started.append(server.start())
        robot = (DockerContainer(ROBOT_IMAGE)
                 .with_name(f"fleetctl-bundle-robot-{suffix}").with_network(network)
                 .with_command(["sleep", "infinity"])
                 .with_volume_mapping(str(bundle), "/mnt/bundle", "ro")
                 .with_volume_mapping(str(WHEELS / "base"), "/wheels/base", "ro")
                 .with_volume_mapping(str(WHEELS / "ros"), "/wheels/ros", "ro")
                 .with_env("PIP_NO_INDEX", "1")
                 .with_env("PIP_FIND_LINKS", "/wheels/base /wheels/ros")
                 .with_env("PIP_DISABLE_PIP_VERSION_CHECK", "1")
                 .with_kwargs(cap_add=["NET_ADMIN"], devices=["/dev/net/tun:/dev/net/tun"]))
        started.append(robot.start())
        # The server's tunnel is up before the robot dials it.
        wait_until(lambda: "WireGuard wg0 up" in _logs(server), 20.0,
                   describe="the server's WireGuard")
        # The operator copies the bundle over; a root shell on a robot without sudo installed.
        _exec(robot, f"cp -a /mnt/bundle {BUNDLE}\n"
                     "printf '#!/bin/sh\\nexec \"$@\"\\n' > /usr/local/bin/sudo\n"
                     "chmod 0755 /usr/local/bin/sudo")
        yield Deployment(server, robot, bundle, fleet_dir)
    finally:
        for container in reversed(started):
            container.stop()
        network.remove()
        client.close()


def _client_in_the_foreground(robot: Any, blocks: dict[str, str], log: str) -> None:
    """The client in the foreground, as the README says (its output goes to *log* here)."""
    robot.get_wrapped_container().exec_run(
        ["bash", "-c", f"{{\n{blocks['client-foreground']}}} >{log} 2>&1"],
        workdir=BUNDLE, detach=True)


def test_readme_blocks_bring_the_robot_online(deployment: Deployment) -> None:
    blocks = readme_blocks((deployment.bundle / "README.md").read_text())
    robot, server = deployment.robot, deployment.server
    for name in ROBOT_BLOCKS:
        _exec(robot, blocks[name], workdir=BUNDLE)
    assert "latest handshake" in _exec(robot, "wg show fleet0")

    _client_in_the_foreground(robot, blocks, "/tmp/client.log")

    def online() -> bool:
        return any(r.get("name") == ROBOT and r.get("online") for r in _robots(server))

    try:
        wait_until(online, ONLINE_DEADLINE_S, poll_s=0.5, describe=f"{ROBOT} online")
    except Exception:
        log = _exec(robot, "cat /tmp/client.log || true")
        pytest.fail(f"{ROBOT} not online in /robots within {ONLINE_DEADLINE_S:.0f} s\n"
                    f"--- client ---\n{log[-3000:]}\n--- server ---\n{_logs(server)}")
    log = _exec(robot, "cat /tmp/client.log")
    # It reached the server over the tunnel and was identified by its WireGuard address.
    assert "connected to ws://10.8.0.1:8080/" in log
    assert f"authenticated as {ROBOT}" in log
    _update_to_a_new_export(deployment)


def _update_to_a_new_export(deployment: Deployment) -> None:
    """A new export (another MTU and ROS domain) copied over the old bundle, and the
    README's update blocks: the tunnel and the client run with the new values (re-running
    the first install's blocks left the running tunnel as it was)."""
    robot, fleet_yaml = deployment.robot, deployment.fleet_dir / "fleet.yaml"
    fleet_yaml.write_text(fleet_yaml.read_text().replace("mtu_bytes: 1280", "mtu_bytes: 1300")
                          .replace("ros_domain_id: 0", "ros_domain_id: 7"))
    ops.render_fleet(deployment.fleet_dir)
    export_robot(deployment.fleet_dir, ROBOT, deployment.bundle)  # over the mounted bundle
    # The operator copies it over the old one and stops the client in the foreground.
    _exec(robot, f"cp -a /mnt/bundle/. {BUNDLE}/\n"
                 "pkill -x fleetctl || true")
    blocks = readme_blocks((deployment.bundle / "README.md").read_text())
    for name in UPDATE_BLOCKS:
        _exec(robot, blocks[name], workdir=BUNDLE)
    assert "mtu 1300" in _exec(robot, "ip link show fleet0")
    _client_in_the_foreground(robot, blocks, "/tmp/client2.log")
    wait_until(lambda: f"authenticated as {ROBOT}" in _exec(robot, "cat /tmp/client2.log || :"),
               ONLINE_DEADLINE_S, poll_s=0.5, describe=f"{ROBOT} back after the update")
    assert "ROS_DOMAIN_ID=7" in _exec(robot, "cat /etc/fleetctl/fleetctl.env")
