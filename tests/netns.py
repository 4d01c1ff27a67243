"""A veth pair into a network namespace the test creates, with a sink on the far side.

Needs root and ``ip``. The sink (in the namespace) accepts TCP on 5001 (it reads a
16-byte length, then that many bytes, and answers ``k``) and echoes UDP on 5002.
"""

from __future__ import annotations

import os
import select
import shutil
import subprocess
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import pytest

from fleetctl.deploy.dockercli import Completed

NEEDS_ROOT = pytest.mark.skipif(os.geteuid() != 0 or shutil.which("ip") is None,
                                reason="needs root and ip")
SINK_TCP_PORT = 5001
SINK_UDP_PORT = 5002

_SINK = r"""
import socket, sys, threading
tcp = socket.socket(); tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
tcp.bind((sys.argv[1], 5001)); tcp.listen(64)
udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); udp.bind((sys.argv[1], 5002))
def echo():
    while True:
        data, peer = udp.recvfrom(2048); udp.sendto(data, peer)
def serve(conn):
    head = conn.recv(16)
    if head:
        want = int(head.decode().strip()); got = 0
        while got < want:
            chunk = conn.recv(1 << 16)
            if not chunk: break
            got += len(chunk)
        conn.sendall(b"k")
    conn.close()
threading.Thread(target=echo, daemon=True).start()
print("ready", flush=True)
while True:
    conn, _ = tcp.accept()
    threading.Thread(target=serve, args=(conn,), daemon=True).start()
"""


def host_run(argv: Sequence[str]) -> Completed:
    """Run a command on the host (the side of the veth pair the test shapes)."""
    proc = subprocess.run(list(argv), capture_output=True, text=True, check=False)
    return Completed(tuple(argv), proc.returncode, proc.stdout, proc.stderr)


@dataclass
class Link:
    """The host end of the pair (``dev``, shape its egress) and the sink's address."""

    dev: str
    peer_ip: str


def veth_link(tag: int) -> Iterator[Link]:
    """Create namespace ``fcshape<tag>`` with the sink; remove everything afterwards."""
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
