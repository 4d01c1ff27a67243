"""Real tc shaping on a veth pair into a network namespace this test creates (root)."""

from __future__ import annotations

import socket
import time

import pytest

from fleetctl.deploy.shaping import LinkShaper, RateSpec, detect, mbit
from tests.netns import NEEDS_ROOT, Link, host_run

pytestmark = [pytest.mark.netns, NEEDS_ROOT]

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
    caps = detect(host_run, link.dev)
    assert caps.tbf and caps.bfifo, caps
    shaper = LinkShaper(host_run, link.dev, caps)

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
