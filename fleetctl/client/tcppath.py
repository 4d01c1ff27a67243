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
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class TcpInfo:
    """What :class:`AckStall` reads from Linux's ``struct tcp_info``.

    Attributes:
        unacked: Segments sent and not acknowledged (``tcpi_unacked``).
        last_ack_s: Time since the last ACK arrived, seconds (``tcpi_last_ack_recv``).
        srtt_s: Smoothed RTT, seconds (``tcpi_rtt``); not updated while no ACK comes.
    """

    unacked: int
    last_ack_s: float
    srtt_s: float


# struct tcp_info up to tcpi_total_retrans: 8 one-byte fields, then 24 __u32.
_TCP_INFO = struct.Struct("=8B24I")
_LINGER_RESET = struct.pack("ii", 1, 0)  # struct linger {l_onoff = 1, l_linger = 0}
_UNACKED, _LAST_ACK_RECV, _RTT = 4, 12, 15  # indices among the __u32 fields


def read_tcp_info(sock: Any) -> TcpInfo | None:
    """The kernel's view of *sock* (a socket or asyncio's ``TransportSocket``); None where
    ``TCP_INFO`` does not exist (not Linux) or the socket is gone."""
    option = getattr(socket, "TCP_INFO", None)
    if option is None or sock is None:
        return None
    try:
        raw = sock.getsockopt(socket.IPPROTO_TCP, option, _TCP_INFO.size)
    except OSError:
        return None
    if len(raw) < _TCP_INFO.size:
        return None
    words = _TCP_INFO.unpack(raw)[8:]
    return TcpInfo(words[_UNACKED], words[_LAST_ACK_RECV] / 1e3, words[_RTT] / 1e6)


class AckStall:
    """Decides from polled :class:`TcpInfo` whether the path is dead (pure, no I/O).

    Dead: data is unacknowledged, no ACK came for ``max(min_gap_s, rtts x srtt)``, and the
    unacknowledged data has been seen for that long too. The last condition matters after
    an idle spell: ``tcpi_last_ack_recv`` is then large although the data was just sent.
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
        self._busy_since_s: float | None = None  # first poll that saw unacked data

    def gap_s(self, info: TcpInfo) -> float:
        """How long without an ACK means dead, for this connection's RTT."""
        return max(self.min_gap_s, self.rtts * info.srtt_s)

    def next_check_s(self, now_s: float, info: TcpInfo) -> float | None:
        """Seconds from *now_s* until the path could be dead if no ACK comes (0 when it
        already looks dead); None with nothing unacknowledged. Call after :meth:`dead`."""
        if info.unacked == 0 or self._busy_since_s is None:
            return None
        gap = self.gap_s(info)
        # dead() compares with ">": look just after the gap, not on it.
        due = max(gap - info.last_ack_s, self._busy_since_s + gap - now_s)
        return max(0.0, due + 0.001)

    def dead(self, now_s: float, info: TcpInfo) -> bool:
        """Update with a poll at *now_s*; True while the path looks dead."""
        if info.unacked == 0:
            self._busy_since_s = None
            return False
        if self._busy_since_s is None:
            self._busy_since_s = now_s
        gap = self.gap_s(info)
        return info.last_ack_s > gap and now_s - self._busy_since_s > gap

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
