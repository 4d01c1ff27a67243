"""The kernel's view of the robot's TCP path: is it dead, and how to leave it for good.

:func:`read_tcp_info` reads Linux's ``TCP_INFO``; :class:`AckStall` decides from those
readings whether the path went silent (data unacknowledged, no ACK for a few RTTs) or stale
(silent long enough that what the connection holds is no longer worth delivering);
:func:`reset_transport` closes a connection with a TCP RST so that no orphan socket
delivers pre-outage data when the path returns. :class:`~fleetctl.client.transport.RobotLink`
uses all three (docs/recovery.md).
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
from collections import deque
from typing import Any, NamedTuple


class TcpInfo(NamedTuple):
    """What :class:`AckStall` reads from Linux's ``struct tcp_info`` (a tuple: one may be
    read after every write, and with a frozen dataclass a read took 12 µs, not 7).

    Attributes:
        unacked: Segments sent and not acknowledged (``tcpi_unacked``).
        last_ack_s: Time since the last ACK arrived, seconds (``tcpi_last_ack_recv``).
        srtt_s: Smoothed RTT, seconds (``tcpi_rtt``); not updated while no ACK comes.
        rttvar_s: The RTT's mean deviation, seconds (``tcpi_rttvar``: the kernel's RTO is
            about ``srtt + 4 x rttvar``).
        acked_bytes: Sequence space acknowledged so far (``tcpi_bytes_acked``: the data
            bytes plus the SYN's one); None on a kernel older than 4.19.
        sent_bytes: Data bytes sent so far, retransmissions not counted again
            (``tcpi_bytes_sent - tcpi_bytes_retrans``); None on a kernel older than 4.19.
    """

    unacked: int
    last_ack_s: float
    srtt_s: float
    rttvar_s: float = 0.0
    acked_bytes: int | None = None
    sent_bytes: int | None = None


# struct tcp_info up to tcpi_total_retrans: 8 one-byte fields, then 24 __u32; then (Linux
# 4.19 and later) up to tcpi_bytes_retrans: __u64 pacing_rate, max_pacing_rate,
# bytes_acked, bytes_received; 6 __u32 (segs_out .. data_segs_out); __u64 delivery_rate,
# busy_time, rwnd_limited, sndbuf_limited; __u32 delivered, delivered_ce; __u64 bytes_sent,
# bytes_retrans. Only the fields read are unpacked (this runs after every write): unacked
# (byte 24), last_ack_recv (56), rtt and rttvar (68), then bytes_acked (120), bytes_sent
# and bytes_retrans (200).
_TCP_INFO = struct.Struct("=24xI28xI8xII28x")
_TCP_INFO_BYTES = struct.Struct("=24xI28xI8xII44xQ72xQQ")
_LINGER_RESET = struct.pack("ii", 1, 0)  # struct linger {l_onoff = 1, l_linger = 0}
# Sends kept by AckStall: a bound, not a figure (a watch needs the oldest few).
_MAX_SENDS = 64


def read_tcp_info(sock: Any) -> TcpInfo | None:
    """The kernel's view of *sock* (a socket or asyncio's ``TransportSocket``); None where
    ``TCP_INFO`` does not exist (not Linux) or the socket is gone."""
    option = getattr(socket, "TCP_INFO", None)
    if option is None or sock is None:
        return None
    try:
        raw = sock.getsockopt(socket.IPPROTO_TCP, option, _TCP_INFO_BYTES.size)
    except OSError:
        return None
    if len(raw) >= _TCP_INFO_BYTES.size:
        unacked, last_ack, rtt, rttvar, acked, sent, retrans = _TCP_INFO_BYTES.unpack(raw)
        return TcpInfo(unacked, last_ack / 1e3, rtt / 1e6, rttvar / 1e6, acked, sent - retrans)
    if len(raw) < _TCP_INFO.size:
        return None
    unacked, last_ack, rtt, rttvar = _TCP_INFO.unpack_from(raw)
    return TcpInfo(unacked, last_ack / 1e3, rtt / 1e6, rttvar / 1e6)


def read_send_mss(sock: Any) -> int | None:
    """The payload bytes one TCP segment of *sock* carries now (Linux's ``mss_cache``:
    the path MTU less the IP and TCP headers and options); None where it cannot be read."""
    if sock is None:
        return None
    try:
        mss = int(sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_MAXSEG))
    except (OSError, AttributeError):
        return None
    return mss if mss > 0 else None


class AckStall:
    """Decides from polled :class:`TcpInfo` whether the path is dead (pure, no I/O).

    Dead: data is unacknowledged, no ACK came for ``max(min_gap_s, rtts x srtt)``, and the
    unacknowledged data has been seen for that long too: a reading, or a write's own
    reading (:meth:`sent`), that long ago saw bytes sent that the ACKs still do not cover
    (the kernel's byte counts; a reading whose bytes are all ACKed says the path delivered
    since, and the data in flight now is newer). The last condition matters after an idle
    spell, or a late wake-up on a busy host: ``tcpi_last_ack_recv`` is then large although
    the data was just sent.
    A live link, however congested, ACKs what arrives; only a silent path stops the ACKs
    with data outstanding (a receiver that stops reading still ACKs, window probes too).

    A false alarm is cheap and self-correcting, which is why the gap can be short (4
    smoothed RTTs, not the kernel's RTO with its backoff): it only starts an early dial,
    and on a path that is alive but slow the old connection's ACK comes back before the
    new connection's SYN-ACK (the SYN queues behind the data), so the switch is called
    off. On a bloated link the smoothed RTT includes the queue (measured srtt: 0.32 s with
    a 400 ms tbf queue at 1 Mbit/s, so dead after ~1.3 s instead of 0.15 s).

    Stale: dead for ``stale_gaps`` gaps. The old connection is then given up for good:
    what it still holds was sent before the outage, and a retransmission of it that wins
    the race against the new connection's SYN when the path returns is a stale delivery
    (seen in the e2e ``peer`` scenario's 0.5 s cuts: the kernel's second retransmission,
    ~0.6 s after the cut, landed just after the restore and delivered 3 messages).

    Args:
        min_gap_s: Shortest ACK gap taken as dead, seconds (above delayed ACKs: 40 ms).
        rtts: The gap in smoothed RTTs.
        stale_gaps: How many gaps without an ACK make the path stale.
    """

    def __init__(self, min_gap_s: float, rtts: float, stale_gaps: float = 2.0) -> None:
        self.min_gap_s = min_gap_s
        self.rtts = rtts
        self.stale_gaps = stale_gaps
        # When data was seen sent: (seconds, TcpInfo.sent_bytes by then), oldest first,
        # from readings and from writes (:meth:`sent`); those whose bytes are all ACKed
        # are dropped, so the first one says since when the oldest unacknowledged byte
        # has been in flight at the latest.
        self._sends: deque[tuple[float, int | None]] = deque()

    @property
    def _busy_since_s(self) -> float | None:
        return self._sends[0][0] if self._sends else None

    def gap_s(self, info: TcpInfo) -> float:
        """How long without an ACK means dead, for this connection's RTT."""
        return max(self.min_gap_s, self.rtts * info.srtt_s)

    def in_flight_s(self, now_s: float) -> float:
        """Since when (seconds before *now_s*) the data in flight has been watched; 0
        with nothing in flight."""
        return 0.0 if self._busy_since_s is None else now_s - self._busy_since_s

    def next_check_s(self, now_s: float, info: TcpInfo) -> float | None:
        """Seconds from *now_s* until the path could be dead if no ACK comes (0 when it
        already looks dead); None with nothing unacknowledged. Call after :meth:`dead`."""
        if info.unacked == 0 or self._busy_since_s is None:
            return None
        gap = self.gap_s(info)
        # dead() compares with ">": look just after the gap, not on it.
        due = max(gap - info.last_ack_s, self._busy_since_s + gap - now_s)
        return max(0.0, due + 0.001)

    @property
    def watching(self) -> bool:
        """Whether data is in flight as far as the readings so far show: a write's own
        reading (:meth:`sent`) matters only then (otherwise the watchdog waits for the
        write and reads at once)."""
        return bool(self._sends)

    def sent(self, now_s: float, info: TcpInfo | None) -> None:
        """Note a reading taken right after a write at *now_s*: what it sent is in flight
        from then on (no verdict: the watchdog's readings give those)."""
        if info is not None:
            self._note(now_s, info)

    def dead(self, now_s: float, info: TcpInfo) -> bool:
        """Update with a poll at *now_s*; True while the path looks dead."""
        self._note(now_s, info)
        busy_since = self._busy_since_s
        if busy_since is None:
            return False
        gap = self.gap_s(info)
        return info.last_ack_s > gap and now_s - busy_since > gap

    def _note(self, now_s: float, info: TcpInfo) -> None:
        """Keep the sends whose bytes are not all ACKed, and this one if it sent more.

        Why: two readings that both see data in flight do not show that data was in
        flight in between. A watchdog that wakes late on a busy host read data just
        written, after the ACK of what the previous reading saw, and took the time since
        that ACK for silence: a dead path, and a switch to the standby on a live link.
        The kernel's byte counts tell the two apart, and the writes' own readings say
        when the data in flight now was sent (a cut soon after an ACK is seen as soon as
        before). ``tcpi_bytes_acked`` counts the SYN of a connecting socket too, so the
        comparison errs by that byte: at worst a send is dropped with its last byte
        unacknowledged, and the watch runs from a later one.
        Without the counts (a kernel before 4.19) the first reading that saw data in
        flight starts the watch until one sees none, as before.
        """
        sends = self._sends
        if info.unacked == 0:
            sends.clear()
            return
        acked = info.acked_bytes
        if acked is not None:
            while sends and sends[0][1] is not None and sends[0][1] <= acked:
                sends.popleft()
        if len(sends) >= _MAX_SENDS:
            return  # the oldest decide; a newer send is noted once they are ACKed
        sent, last = info.sent_bytes, sends[-1][1] if sends else None
        if not sends or (sent is not None and last is not None and sent > last):
            sends.append((now_s, sent))

    def stale(self, now_s: float, info: TcpInfo) -> bool:
        """True when the path has been dead for ``stale_gaps`` gaps (call after
        :meth:`dead`, which tracks how long data has been in flight)."""
        if info.unacked == 0 or self._busy_since_s is None:
            return False
        gap = self.stale_gaps * self.gap_s(info)
        return info.last_ack_s > gap and now_s - self._busy_since_s > gap


def reset_transport(transport: asyncio.Transport) -> None:
    """Close *transport* with a TCP reset (``SO_LINGER`` 0).

    Why: a plain ``close()`` (asyncio's ``abort()`` too) leaves unacknowledged data to an
    orphan socket that keeps retransmitting it with backoff and delivers it whenever the
    path returns: frames published before an outage reaching the relay after it. With a
    zero linger the kernel discards the send queue at once and sends a RST instead.
    """
    sock = transport.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, _LINGER_RESET)
    transport.abort()
