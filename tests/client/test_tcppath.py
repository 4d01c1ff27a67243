"""The kernel's view of the TCP path: dead and stale paths, TCP_INFO, the reset (issue 19)."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time

import pytest

from fleetctl.client.tcppath import AckStall, TcpInfo, read_tcp_info, reset_transport
from fleetctl.deploy.shaping import LinkShaper, RateSpec, detect, mbit
from tests.netns import NEEDS_ROOT, SINK_TCP_PORT, Link, host_run

# -- AckStall (pure) -------------------------------------------------------------------


def info(unacked: int, last_ack_s: float, srtt_s: float = 0.002) -> TcpInfo:
    return TcpInfo(unacked=unacked, last_ack_s=last_ack_s, srtt_s=srtt_s)


def test_a_busy_path_without_acks_is_dead_after_the_gap() -> None:
    stall = AckStall(0.15, 8.0)
    assert not stall.dead(0.00, info(4, 0.01))  # ACKs coming
    assert not stall.dead(0.05, info(6, 0.06))
    assert not stall.dead(0.15, info(6, 0.16))  # busy for 0.15 s: not over the gap yet
    assert stall.dead(0.20, info(6, 0.21))


def test_data_sent_after_an_idle_spell_is_not_a_false_alarm() -> None:
    """After idling, the last ACK is long ago although the data was just sent."""
    stall = AckStall(0.15, 8.0)
    assert not stall.dead(0.0, info(0, 5.0))  # idle
    assert not stall.dead(0.05, info(2, 5.05))  # sent just now: watched from here
    assert not stall.dead(0.10, info(0, 0.01))  # ACKed within the RTT
    assert not stall.dead(0.15, info(3, 0.06))
    assert not stall.dead(0.25, info(3, 0.16))  # busy for only 0.10 s
    assert stall.dead(0.35, info(3, 0.26))


def test_a_path_dead_for_two_gaps_is_stale() -> None:
    """Dead after one gap (an early dial, the old connection kept), stale after two (the
    old connection is reset: what it holds would arrive stale)."""
    stall = AckStall(0.15, 4.0, stale_gaps=2.0)
    assert not stall.dead(0.0, info(4, 0.01))
    assert stall.dead(0.2, info(4, 0.21)) and not stall.stale(0.2, info(4, 0.21))
    assert stall.dead(0.29, info(4, 0.30)) and not stall.stale(0.29, info(4, 0.30))
    assert stall.stale(0.31, info(4, 0.32))
    assert not stall.stale(0.31, info(4, 0.01))  # an ACK came: neither dead nor stale
    assert not stall.stale(0.5, info(0, 5.0))  # nothing in flight


def test_stale_scales_with_the_smoothed_rtt_too() -> None:
    stall = AckStall(0.15, 4.0, stale_gaps=2.0)
    stall.dead(0.0, info(5, 0.0, srtt_s=0.1))  # dead after 0.4 s, stale after 0.8 s
    assert not stall.stale(0.7, info(5, 0.7, srtt_s=0.1))
    assert stall.stale(0.9, info(5, 0.9, srtt_s=0.1))


async def test_reset_transport_sends_a_reset_not_a_fin() -> None:
    """The peer sees ECONNRESET, not an orderly end of stream: the kernel discarded the
    send queue (an orphan socket would retransmit it when the path returns)."""
    accepted: asyncio.Queue[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = (
        asyncio.Queue())

    async def on_client(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        await accepted.put((r, w))

    server = await asyncio.start_server(on_client, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        _, writer = await asyncio.open_connection("127.0.0.1", port)
        reader, peer = await accepted.get()
        reset_transport(writer.transport)
        with pytest.raises(ConnectionResetError):
            await asyncio.wait_for(reader.read(1), 5.0)
        peer.close()


def test_the_gap_scales_with_the_smoothed_rtt() -> None:
    stall = AckStall(0.15, 8.0)
    slow = info(5, 0.5, srtt_s=0.1)  # a satellite-like 100 ms RTT: dead after 0.8 s
    assert stall.gap_s(slow) == pytest.approx(0.8)
    stall.dead(0.0, slow)
    assert not stall.dead(0.6, info(5, 0.6, srtt_s=0.1))
    assert stall.dead(0.9, info(5, 0.9, srtt_s=0.1))


def test_the_next_look_is_when_the_data_in_flight_could_be_dead() -> None:
    """The watchdog sleeps until then instead of polling (no wake-ups while idle)."""
    stall = AckStall(0.15, 8.0)
    idle = info(0, 5.0)
    stall.dead(0.0, idle)
    assert stall.next_check_s(0.0, idle) is None
    sent = info(2, 5.0)  # just sent after idling: the busy time decides
    stall.dead(1.0, sent)
    assert stall.next_check_s(1.0, sent) == pytest.approx(0.151)
    acking = info(2, 0.05)  # busy for 0.2 s, last ACK 50 ms ago: the ACK gap decides
    stall.dead(1.2, acking)
    assert stall.next_check_s(1.2, acking) == pytest.approx(0.101)
    silent = info(2, 0.3)
    assert stall.dead(1.45, silent)
    assert stall.next_check_s(1.45, silent) == 0.0  # dead now: at the outage's pace


# -- TCP_INFO on real sockets ------------------------------------------------------------


@pytest.mark.skipif(not hasattr(socket, "TCP_INFO"), reason="Linux only")
def test_tcp_info_of_a_loopback_connection() -> None:
    with socket.create_server(("127.0.0.1", 0)) as server:
        client = socket.create_connection(server.getsockname())
        peer, _ = server.accept()
        with client, peer:
            client.sendall(b"x" * 1000)
            assert peer.recv(1000)
            deadline = time.monotonic() + 2.0
            got = read_tcp_info(client)
            while got is not None and got.unacked and time.monotonic() < deadline:
                got = read_tcp_info(client)  # the ACK is on its way (loopback: at once)
            assert got is not None
            assert got.unacked == 0
            assert 0 < got.srtt_s < 0.1
            assert got.last_ack_s < 1.0
    assert read_tcp_info(None) is None


@pytest.mark.netns
@NEEDS_ROOT
def test_a_cut_is_detected_and_a_slow_live_link_is_not(link: Link) -> None:
    """Stream into the sink over a 1 Mbit/s link with a 400 ms queue (congested, alive):
    no false alarm in 1.5 s; then cut it: dead once the ACK gap passes 4 smoothed RTTs
    (the queue is in the RTT: ~1.3 s here)."""
    shaper = LinkShaper(host_run, link.dev, detect(host_run, link.dev))
    shaper.set_rate(RateSpec(mbit(1), queue_latency_ms=400))
    stall = AckStall(0.15, 4.0)
    sock = socket.create_connection((link.peer_ip, SINK_TCP_PORT), timeout=5.0)
    try:
        sock.setblocking(False)
        sock.send(f"{1 << 30:16d}".encode())
        chunk = bytes(16384)

        def pump_and_poll(until: float) -> float | None:
            """Keep the send buffer full until *until*; when the path looks dead."""
            while time.monotonic() < until:
                with contextlib.suppress(BlockingIOError):
                    sock.send(chunk)
                got = read_tcp_info(sock)
                assert got is not None
                if stall.dead(time.monotonic(), got):
                    return time.monotonic()
                time.sleep(0.05)  # the poll period of the link, not a synchronization
            return None

        assert pump_and_poll(time.monotonic() + 1.5) is None  # congested, not dead
        got = read_tcp_info(sock)
        assert got is not None
        gap = stall.gap_s(got)
        cut = time.monotonic()
        shaper.cut()
        dead_at = pump_and_poll(cut + 5.0)
        assert dead_at is not None
        assert dead_at - cut < gap + 0.3, (dead_at - cut, gap)
    finally:
        sock.close()
        shaper.clear()

