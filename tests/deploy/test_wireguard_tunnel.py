"""A real WireGuard tunnel from configs fleetctl generated.

Two network namespaces joined by a veth pair (addresses exist only inside them); Debian's
``wireguard-go`` runs in each; ``wg-quick strip`` + ``wg setconf`` apply the generated
configs; a handshake completes and UDP crosses the tunnel, and the server sees the
robot's /32 as the source address.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetctl.deploy import operations as ops

pytestmark = [
    pytest.mark.netns,
    pytest.mark.skipif(
        os.geteuid() != 0 or not all(shutil.which(t) for t in ("wireguard-go", "wg", "wg-quick")),
        reason="needs root, wireguard-go and wireguard-tools",
    ),
]

TAG = f"{os.getpid() % 100000}"
SRV_NS, ROB_NS = f"fcwg-srv-{TAG}", f"fcwg-rob-{TAG}"
SRV_IF, ROB_IF = f"fcwgs{TAG}", f"fcwgr{TAG}"  # <= 15 chars; UAPI sockets are global
VETH_SRV, VETH_ROB = f"fcvs{TAG}", f"fcvr{TAG}"
SRV_UNDERLAY, ROB_UNDERLAY = "10.99.0.1", "10.99.0.2"


def _run(*cmd: str, ns: str | None = None, timeout: float = 10.0) -> str:
    full = ["ip", "netns", "exec", ns, *cmd] if ns else list(cmd)
    res = subprocess.run(full, capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, f"{full}: {res.stderr}"
    return res.stdout


def _wait_for(what: str, check: object, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if callable(check) and check():
            return
        time.sleep(0.05)  # polling interval of a condition with a deadline, not a sync sleep
    pytest.fail(f"timed out after {timeout_s} s waiting for {what}")


def _interface_settings(conf: Path) -> tuple[str, int | None]:
    """Return the [Interface] Address and MTU of a wg-quick config (wg setconf skips them)."""
    address, mtu = "", None
    for line in conf.read_text().splitlines():
        key, _, value = (part.strip() for part in line.partition("="))
        if key == "Address":
            address = value
        elif key == "MTU":
            mtu = int(value)
    return address, mtu


def _bring_up(ns: str, iface: str, conf: Path, routes: list[str]) -> subprocess.Popen[bytes]:
    proc = subprocess.Popen(["ip", "netns", "exec", ns, "wireguard-go", "-f", iface],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sock = Path(f"/var/run/wireguard/{iface}.sock")
    _wait_for(f"{sock}", lambda: sock.exists() or proc.poll() is not None)
    assert proc.poll() is None, "wireguard-go exited"
    stripped = conf.with_suffix(".stripped")
    stripped.write_text(_run("wg-quick", "strip", str(conf)))
    _run("wg", "setconf", iface, str(stripped), ns=ns)
    address, mtu = _interface_settings(conf)
    _run("ip", "address", "add", address, "dev", iface, ns=ns)
    _run("ip", "link", "set", iface, "up", *(("mtu", str(mtu)) if mtu else ()), ns=ns)
    for route in routes:  # what wg-quick adds for AllowedIPs wider than the address
        _run("ip", "route", "replace", route, "dev", iface, ns=ns)
    return proc


@pytest.fixture
def namespaces() -> Iterator[None]:
    try:
        for ns in (SRV_NS, ROB_NS):
            _run("ip", "netns", "add", ns)
            _run("ip", "link", "set", "lo", "up", ns=ns)
        _run("ip", "link", "add", VETH_SRV, "netns", SRV_NS, "type", "veth",
             "peer", "name", VETH_ROB, "netns", ROB_NS)
        for ns, dev, addr in ((SRV_NS, VETH_SRV, SRV_UNDERLAY), (ROB_NS, VETH_ROB, ROB_UNDERLAY)):
            _run("ip", "address", "add", f"{addr}/24", "dev", dev, ns=ns)
            _run("ip", "link", "set", dev, "up", ns=ns)
        yield
    finally:
        for ns in (SRV_NS, ROB_NS):
            subprocess.run(["ip", "netns", "delete", ns], capture_output=True)


_UDP_RECEIVER = """
import socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind((sys.argv[1], 0))
s.settimeout(10.0)
print(s.getsockname()[1], flush=True)
data, peer = s.recvfrom(2048)
print(peer[0], data.decode(), flush=True)
"""


def test_tunnel_carries_traffic(namespaces: None, tmp_path: Path) -> None:
    fleet_dir = tmp_path / "fleet"
    ops.create_fleet(fleet_dir, endpoint=f"{SRV_UNDERLAY}:51820")
    robot = ops.add_robot(fleet_dir, "husky1").robot
    fleet = ops.describe_fleet(fleet_dir).fleet
    procs: list[subprocess.Popen[bytes]] = []
    try:
        procs.append(_bring_up(SRV_NS, SRV_IF, fleet_dir / "server/wireguard/wg0.conf", []))
        procs.append(_bring_up(ROB_NS, ROB_IF, fleet_dir / "robots/husky1/wireguard/wg0.conf",
                               [str(fleet.subnet)]))
        # PersistentKeepalive makes the robot start the handshake as soon as it is configured.
        _wait_for("a WireGuard handshake", lambda: _handshake_done(SRV_NS, SRV_IF))
        _udp_over_tunnel(str(fleet.server_ip), str(robot.ip))
    finally:
        for proc in procs:
            proc.terminate()
            proc.wait(timeout=10)


def _handshake_done(ns: str, iface: str) -> bool:
    fields = _run("wg", "show", iface, "latest-handshakes", ns=ns).split()
    return len(fields) == 2 and int(fields[1]) > 0


def _udp_over_tunnel(server_ip: str, robot_ip: str) -> None:
    receiver = subprocess.Popen(
        ["ip", "netns", "exec", SRV_NS, sys.executable, "-c", _UDP_RECEIVER, server_ip],
        stdout=subprocess.PIPE, text=True)
    try:
        assert receiver.stdout is not None
        port = int(receiver.stdout.readline())
        send = ("import socket, sys; socket.socket(socket.AF_INET, socket.SOCK_DGRAM)"
                ".sendto(b'hello fleet', (sys.argv[1], int(sys.argv[2])))")
        _run(sys.executable, "-c", send, server_ip, str(port), ns=ROB_NS)
        out, _ = receiver.communicate(timeout=15)
        # The server sees the robot's WireGuard /32: what the auth map identifies it by.
        assert out.split() == [robot_ip, "hello", "fleet"]
    finally:
        if receiver.poll() is None:
            receiver.kill()
            receiver.wait()
