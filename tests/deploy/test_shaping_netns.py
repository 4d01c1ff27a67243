"""Real tc shaping on a veth pair into a network namespace this test creates (root)."""

from __future__ import annotations

import os
import select
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import pytest

from fleetctl.deploy.dockercli import Completed
from fleetctl.deploy.shaping import LinkShaper, RateSpec, detect, mbit

pytestmark = [
    pytest.mark.netns,
    pytest.mark.skipif(os.geteuid() != 0 or shutil.which("ip") is None, reason="needs root"),
]

_SINK = r"""
import socket, sys, threading
tcp = socket.socket(); tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
tcp.bind((sys.argv[1], 5001)); tcp.listen()
udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); udp.bind((sys.argv[1], 5002))
def echo():
    while True:
        data, peer = udp.recvfrom(2048); udp.sendto(data, peer)
threading.Thread(target=echo, daemon=True).start()
print("ready", flush=True)
while True:
    conn, _ = tcp.accept()
    want = int(conn.recv(16).decode().strip()); got = 0
    while got < want:
        chunk = conn.recv(1 << 16)
        if not chunk: break
        got += len(chunk)
    conn.sendall(b"k"); conn.close()
"""


def _host_run(argv: Sequence[str]) -> Completed:
    proc = subprocess.run(list(argv), capture_output=True, text=True, check=False)
    return Completed(tuple(argv), proc.returncode, proc.stdout, proc.stderr)


@dataclass
class Link:
    dev: str
    peer_ip: str


@pytest.fixture
def link() -> Iterator[Link]:
    tag = os.getpid() % 200 + 20
    ns, host_dev, ns_dev = f"fcshape{tag}", f"fcsh{tag}a", f"fcsh{tag}b"
    host_ip, peer_ip = f"10.250.{tag}.1", f"10.250.{tag}.2"
    setup = [
        ["ip", "netns", "add", ns],
        ["ip", "link", "add", host_dev, "type", "veth", "peer", "name", ns_dev],
        ["ip", "link", "set", ns_dev, "netns", ns],
        ["ip", "addr", "add", f"{host_ip}/30", "dev", host_dev],
        ["ip", "link", "set", host_dev, "up"],
        ["ip", "netns", "exec", ns, "ip", "addr", "add", f"{peer_ip}/30", "dev", ns_dev],
        ["ip", "netns", "exec", ns, "ip", "link", "set", ns_dev, "up"],
        ["ip", "netns", "exec", ns, "ip", "link", "set", "lo", "up"],
    ]
    sink = None
    try:
        for argv in setup:
            subprocess.run(argv, check=True, capture_output=True)
        sink = subprocess.Popen(
            ["ip", "netns", "exec", ns, sys.executable, "-c", _SINK, peer_ip],
            stdout=subprocess.PIPE, text=True,
        )
        assert sink.stdout is not None
        ready, _, _ = select.select([sink.stdout], [], [], 10.0)
        assert ready and sink.stdout.readline().strip() == "ready"
        yield Link(host_dev, peer_ip)
    finally:
        if sink is not None:
            sink.kill()
            sink.wait()
        subprocess.run(["ip", "link", "del", host_dev], capture_output=True, check=False)
        subprocess.run(["ip", "netns", "del", ns], capture_output=True, check=False)


def _throughput_bit_s(peer_ip: str, nbytes: int) -> float:
    with socket.create_connection((peer_ip, 5001), timeout=10.0) as sock:
        sock.sendall(f"{nbytes:<16}".encode())
        start = time.monotonic()
        sock.sendall(bytes(nbytes))
        assert sock.recv(1) == b"k"
        return nbytes * 8 / (time.monotonic() - start)


def _echo_ok(peer_ip: str, timeout_s: float) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.settimeout(timeout_s)
        sock.sendto(b"ping", (peer_ip, 5002))
        try:
            return sock.recvfrom(16)[0] == b"ping"
        except TimeoutError:
            return False


def test_rate_live_change_cut_and_restore(link: Link) -> None:
    caps = detect(_host_run, link.dev)
    assert caps.tbf and caps.bfifo, caps
    shaper = LinkShaper(_host_run, link.dev, caps)

    shaper.set_rate(RateSpec(mbit(16)))
    slow = _throughput_bit_s(link.peer_ip, 1_500_000)  # ~0.75 s at 16 Mbit
    assert mbit(16) * 0.7 < slow < mbit(16) * 1.1, slow

    shaper.set_rate(RateSpec(mbit(64)))  # live change, same qdisc
    assert shaper.commands[-1][2] == "change"
    fast = _throughput_bit_s(link.peer_ip, 4_000_000)
    assert mbit(64) * 0.6 < fast < mbit(64) * 1.1, fast

    assert _echo_ok(link.peer_ip, 2.0)
    shaper.cut()
    assert not _echo_ok(link.peer_ip, 0.3)  # silently dropped, like a radio gap
    shaper.restore()
    assert _echo_ok(link.peer_ip, 2.0)
    assert "64000000bit" in shaper.commands[-1]
    shaper.clear()
