"""`up`, and changes to fleet.yaml reaching a running deployment, on the real server image.

A server that fails at its start: `up` exits 1 naming it with its last log lines (it said
`fleet is up` while the server restarted every few seconds).

`init` -> `up` (WireGuard on, published on loopback) -> the page answers on the HTTPS port
-> fleet.yaml's `https_port` and `wireguard_port` edited by hand -> `render` -> the page
answers on the new port, the old one is closed, the container publishes the new ports and
`status` is healthy -> `down --delete-data`.

Before 2026-12-06 `render` restarted the server with the new server.yaml: it listened on
the new port behind the container's old port mapping, so the page was on neither port
while `status` said healthy, until a `fleetctl up`.
"""

from __future__ import annotations

import random
import socket
import ssl
import subprocess
import urllib.error
import urllib.request
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetctl.waiting import wait_until
from tests.deploy.test_lifecycle_docker import FLEETCTL, Operator, _free_port, _images_present

pytestmark = [pytest.mark.docker, pytest.mark.slow]

PAGE_TIMEOUT_S = 60.0


def _page_answers(port: int, cert: Path) -> bool:
    context = ssl.create_default_context(cafile=str(cert))
    try:
        with urllib.request.urlopen(f"https://127.0.0.1:{port}/", context=context,
                                    timeout=2) as res:
            return bool(res.status == 200)
    except (urllib.error.URLError, OSError):
        return False


def _new_fleet(tmp_path: Path, *init: str) -> tuple[Operator, Path, str]:
    """A new fleet on free ports (*init*: more `init` options), its operator and a project
    name."""
    if not _images_present():
        pytest.skip("images fleetctl/server and client not built")
    if not Path("/dev/net/tun").exists():
        pytest.skip("no /dev/net/tun: WireGuard cannot run here")
    fleet = tmp_path / "yard"
    op = Operator(tmp_path, fleet)
    op.run("init", str(fleet), "--endpoint", f"127.0.0.1:{_free_port(socket.SOCK_DGRAM)}",
           "--https-port", str(_free_port()), *init)
    return op, fleet, f"fleetctllive{uuid.uuid4().hex[:8]}"


@pytest.fixture
def running(tmp_path: Path) -> Iterator[tuple[Operator, Path, str]]:
    op, fleet, project = _new_fleet(tmp_path)
    op.run("add-robot", "husky1")
    try:
        op.run("up", "--bind", "127.0.0.1", "--project", project)
        yield op, fleet, project
    finally:
        if (fleet / ".compose" / "state.json").is_file():
            op.run("down", "--delete-data", ok=False)


def _published(project: str) -> str:
    return subprocess.run(
        ["docker", "ps", "--filter", f"label=com.docker.compose.project={project}",
         "--filter", "label=com.docker.compose.service=server", "--format", "{{.Ports}}"],
        capture_output=True, text=True, check=True).stdout


def test_render_moves_a_running_servers_published_ports(
        running: tuple[Operator, Path, str]) -> None:
    op, fleet, project = running
    cert = fleet / "server" / "tls" / "cert.pem"
    fleet_yaml = fleet / "fleet.yaml"
    old = int(op.json("list")["fleet"]["https_port"])
    wait_until(lambda: _page_answers(old, cert), PAGE_TIMEOUT_S, describe="the page")
    new, udp = _free_port(), _free_port(socket.SOCK_DGRAM)
    text = fleet_yaml.read_text()
    wg = op.json("list")["fleet"]["wireguard_port"]
    fleet_yaml.write_text(text.replace(f"https_port: {old}", f"https_port: {new}")
                          .replace(f"wireguard_port: {wg}", f"wireguard_port: {udp}"))
    op.run("render")
    wait_until(lambda: _page_answers(new, cert), PAGE_TIMEOUT_S,
               describe=f"the page on the new https_port {new}")
    assert not _page_answers(old, cert)
    ports = _published(project)
    assert f"127.0.0.1:{new}->{new}/tcp" in ports and f"127.0.0.1:{udp}->{udp}/udp" in ports
    wait_until(lambda: op.json("status")["healthy"], PAGE_TIMEOUT_S,
               describe="a healthy status")


def test_up_says_so_when_the_server_does_not_start(tmp_path: Path) -> None:
    """A registry database that is not one (a damaged disk, a wrong file restored into the
    volume): the server exits 3 at every start."""
    op, _fleet, project = _new_fleet(tmp_path)
    volume = f"{project}_server-data"
    try:
        subprocess.run(["docker", "run", "--rm", "--user", "root", "-v", f"{volume}:/data",
                        "--entrypoint", "sh", "fleetctl/server:latest", "-c",
                        "head -c 8192 /dev/zero | tr '\\0' x > /data/fleet.db"],
                       check=True, capture_output=True, timeout=60)
        res = subprocess.run([FLEETCTL, "up", "--bind", "127.0.0.1", "--project", project],
                             cwd=tmp_path, env=op.env, text=True, capture_output=True,
                             timeout=300, check=False)
        assert res.returncode == 1, res.stdout + res.stderr
        assert "fleet is up" not in res.stdout
        error = res.stderr.splitlines()[-1]
        assert error.startswith("fleetctl: error: server "), error
        assert "it did not start; its last lines: " in error
        assert "file is not a database" in error
    finally:
        op.run("down", "--delete-data", "--project", project, ok=False)
        subprocess.run(["docker", "volume", "rm", "-f", volume], capture_output=True,
                       check=False)


def test_up_without_wireguard_names_a_docker_network_on_the_fleet_subnet(
        tmp_path: Path) -> None:
    """Without WireGuard the compose network is the fleet subnet: one that overlaps another
    Docker network was compose's "Pool overlaps with other one on this address space" and
    `compose up failed`, after the compose file and state were written."""
    subnet = f"10.{random.randint(200, 250)}.{random.randint(0, 255)}.0/24"
    op, fleet, project = _new_fleet(tmp_path, "--subnet", subnet)
    clash = f"fleetctl-clash-{uuid.uuid4().hex[:8]}"
    subprocess.run(["docker", "network", "create", "--subnet", subnet, clash], check=True,
                   capture_output=True, timeout=60)
    try:
        res = subprocess.run([FLEETCTL, "up", "--wireguard", "off", "--bind", "127.0.0.1",
                              "--project", project], cwd=tmp_path, env=op.env, text=True,
                             capture_output=True, timeout=300, check=False)
        assert res.returncode == 4, res.stdout + res.stderr
        assert res.stderr.splitlines()[-1] == (
            f"fleetctl: error: {fleet}/fleet.yaml: subnet {subnet} overlaps Docker network "
            f"'{clash}' ({subnet}): without WireGuard the compose network is the fleet "
            "subnet, and Docker refuses two that overlap; remove that network, or run with "
            "WireGuard (--wireguard on, which needs /dev/net/tun)")
        assert not (fleet / ".compose").exists()
    finally:
        subprocess.run(["docker", "network", "rm", clash], capture_output=True, check=False)


def _volumes(project: str) -> list[str]:
    return sorted(subprocess.run(
        ["docker", "volume", "ls", "-q", "--filter",
         f"label=com.docker.compose.project={project}"],
        capture_output=True, text=True, check=True).stdout.split())


def test_down_delete_data_deletes_the_volumes_of_an_earlier_mode(tmp_path: Path) -> None:
    """`up`, `down`, `up --replicas 2`, `down --delete-data` left the single server's
    `server-data` volume (its registry, sessions and recordings): compose's `down -v`
    deletes only the volumes of the compose file it is given, the replicas' one."""
    op, _fleet, project = _new_fleet(tmp_path)
    try:
        op.run("up", "--bind", "127.0.0.1", "--project", project)
        op.run("down")
        assert _volumes(project) == [f"{project}_server-data"]  # plain down keeps it
        op.run("up", "--bind", "127.0.0.1", "--project", project, "--replicas", "2")
        assert {f"{project}_server-data", f"{project}_relay-1-data"} <= set(_volumes(project))
        op.run("down", "--delete-data")
        assert _volumes(project) == []
    finally:
        op.run("down", "--delete-data", ok=False)
