"""The kernel's view of the TCP path: dead and stale paths, TCP_INFO, the reset (issue 19)."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time
from collections.abc import Callable

import pytest

from fleetctl.client.tcppath import (
    AckStall,
    TcpInfo,
    read_send_mss,
    read_tcp_info,
    reset_transport,
)
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


def sent(unacked: int, last_ack_s: float, acked_bytes: int, sent_bytes: int) -> TcpInfo:
    """A reading with the kernel's byte counts (Linux 4.19 and later)."""
    return TcpInfo(unacked=unacked, last_ack_s=last_ack_s, srtt_s=0.004, rttvar_s=0.006,
                   acked_bytes=acked_bytes, sent_bytes=sent_bytes)


def test_a_late_reading_of_data_written_after_an_ack_is_not_a_dead_path() -> None:
    """A busy host (the demo under load, 2026-12-06): a reading saw data in flight, its
    ACK came a moment later, and the next reading woke 93 ms late, after the process had
    written again: data in flight and the last ACK 0.244 s ago, so the path was taken for
    dead and the robot swapped to its standby, on a live loopback link. What was in flight
    at the first reading was acknowledged: no data waited 0.244 s for an ACK."""
    stall = AckStall(0.15, 4.0)
    assert not stall.dead(0.0, sent(3, 0.0, acked_bytes=1001, sent_bytes=4000))
    late = sent(5, 0.244, acked_bytes=4001, sent_bytes=9000)  # 0-4000 ACKed at 0.0
    assert not stall.dead(0.244, late)
    assert not stall.stale(0.244, late)
    assert stall.next_check_s(0.244, late) == pytest.approx(0.151)  # watched from here
    # The same data still unacknowledged a gap later: dead then (and stale after two).
    assert not stall.dead(0.35, sent(5, 0.35, acked_bytes=4001, sent_bytes=9000))
    assert stall.dead(0.40, sent(6, 0.40, acked_bytes=4001, sent_bytes=9500))
    assert stall.stale(0.55, sent(6, 0.55, acked_bytes=4001, sent_bytes=9500))


def test_a_cut_while_streaming_is_dead_one_gap_after_the_first_reading() -> None:
    """ACKs that cover only part of what the first reading saw in flight (the path died
    with data on it) do not restart the watch: detection is as quick as before."""
    stall = AckStall(0.15, 4.0)
    assert not stall.dead(0.0, sent(8, 0.001, acked_bytes=50_001, sent_bytes=80_000))
    cut = sent(9, 0.155, acked_bytes=70_001, sent_bytes=90_000)  # last ACK at 0.005
    assert stall.dead(0.16, cut)
    assert stall.stale(0.31, sent(9, 0.305, acked_bytes=70_001, sent_bytes=90_000))


def test_a_cut_soon_after_an_ack_is_dead_a_gap_after_the_write_into_it() -> None:
    """What the first reading saw in flight is ACKed, the link writes more (the write's
    own reading notes it, :meth:`AckStall.sent`) and the path dies: dead a gap after that
    write, not a gap after the next reading (the e2e dropout's cut, first version of the
    fix: dead after 0.23-0.30 s of silence and stale after 0.39-0.45 s, not 0.15 and
    0.30)."""
    stall = AckStall(0.15, 4.0)
    assert not stall.dead(0.0, sent(3, 0.0, acked_bytes=1001, sent_bytes=4000))
    stall.sent(0.01, sent(2, 0.009, acked_bytes=4001, sent_bytes=6000))  # then the cut
    assert not stall.dead(0.151, sent(2, 0.150, acked_bytes=4001, sent_bytes=6000))
    assert stall.dead(0.165, sent(2, 0.164, acked_bytes=4001, sent_bytes=6000))
    assert stall.stale(0.315, sent(2, 0.314, acked_bytes=4001, sent_bytes=6000))


def test_retransmissions_do_not_restart_the_watch() -> None:
    """A dead path's retransmissions (RTO, tail loss probes) are not new data: the byte
    count sent stays, so the watch goes on (TcpInfo.sent_bytes leaves them out)."""
    stall = AckStall(0.15, 4.0)
    assert not stall.dead(0.0, sent(4, 0.0, acked_bytes=1, sent_bytes=6000))
    assert stall.dead(0.2, sent(4, 0.2, acked_bytes=1, sent_bytes=6000))


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
            # The byte counts (Linux 4.19+): the data, and the SYN's sequence number.
            assert got.sent_bytes == 1000
            assert got.acked_bytes == 1001
    assert read_tcp_info(None) is None


def test_the_send_mss_is_the_path_s_segment_less_headers_and_options() -> None:
    """A peer advertising 1200 bytes (as a path of a smaller MTU does): the robot's
    segments carry 1188, the 12 of TCP's timestamp option taken off."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        server.setsockopt(socket.IPPROTO_TCP, socket.TCP_MAXSEG, 1200)
        client = socket.create_connection(server.getsockname())
        peer, _ = server.accept()
        with client, peer:
            assert read_send_mss(client) == 1188
    assert read_send_mss(None) is None
    closed = socket.socket()
    closed.close()
    assert read_send_mss(closed) is None


def _read(sock: socket.socket) -> TcpInfo:
    got = read_tcp_info(sock)
    assert got is not None
    return got


def _wait_for(sock: socket.socket, done: Callable[[TcpInfo], bool]) -> TcpInfo:
    """Read *sock*'s TCP_INFO until *done* says so (at most 5 s)."""
    deadline = time.monotonic() + 5.0
    while not done(got := _read(sock)):
        assert time.monotonic() < deadline, got
        time.sleep(0.002)  # the reading's pace, not a synchronization
    return got


def _exchange(client: socket.socket, peer: socket.socket, data: bytes) -> TcpInfo:
    """*client* sends *data* and reads its TCP_INFO at once; *peer* answers with a byte,
    as the relay answers a ping (the answer carries the ACK; in this request-response
    mode the peer's kernel otherwise delays its ACK by 40 ms or more)."""
    client.send(data)
    got = _read(client)
    peer.recv(4096)
    peer.send(b"r")
    client.recv(16)
    return got


@pytest.mark.skipif(not hasattr(socket, "TCP_INFO"), reason="Linux only")
def test_a_late_reading_on_a_live_loopback_connection_is_not_a_dead_path() -> None:
    """The busy host's false alarm with the kernel's own readings: one reading sees data in
    flight; its ACK comes (the watchdog, late, misses the moment nothing was in flight);
    more than a gap after that ACK the process writes again and reads at once, before
    the answer that ACKs it. Data in flight, no ACK for over a gap: the old rule called
    the live path dead."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        client = socket.create_connection(server.getsockname())
        peer, _ = server.accept()
        with client, peer:
            for _ in range(4):  # out of quick-ACK mode, into request-response
                _exchange(client, peer, b"w" * 100)
            deadline = time.monotonic() + 20.0
            checked = 0
            while checked < 3:  # three times where the readings show the case
                assert time.monotonic() < deadline, f"only {checked} readings showed it"
                stall = AckStall(0.15, 4.0)
                first = _exchange(client, peer, b"a" * 100)
                stall.dead(time.monotonic() - 0.001, first)  # read as it was sent
                _wait_for(client, lambda got: got.unacked == 0)  # not shown to stall
                _wait_for(client, lambda got: got.last_ack_s > 0.2)
                late = _exchange(client, peer, b"b" * 100)
                if first.unacked == 0 or late.unacked == 0:
                    continue  # ACKed at once (quick-ACK mode): not the case, again
                assert late.last_ack_s > stall.gap_s(late)
                assert not stall.dead(time.monotonic(), late), late
                checked += 1


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

