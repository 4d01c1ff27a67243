"""The robot link's transport settings that are not in ``client.yaml``.

They tune :class:`~fleetctl.client.transport.RobotLink` (timeouts, batching, the dead-path
detection of :mod:`fleetctl.client.tcppath`, the uplink deflate); tests and benchmarks
shorten them, deployments keep the defaults.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from fleetctl.client.dialer import DialSettings
from fleetctl.client.slowdeflate import SlowDeflateSettings
from fleetctl.linkdeflate import DEFAULT_MAX_MESSAGE_BYTES


@dataclass(frozen=True)
class LinkTuning:
    """Transport settings that are not in ``client.yaml`` (defaults suit most links).

    Attributes:
        open_timeout_s: Limit of one connection attempt (TCP + TLS + upgrade), seconds.
        dial: How the TCP connection is raced (see :mod:`fleetctl.client.dialer`).
        failover_after_s: With several replicas (``server_url`` a list), the current one
            has this head start in a dial before the others join the race, seconds
            (:func:`~fleetctl.client.dialer.dial_first`); a replica that refuses is left
            at once.
        keepalive_interval_s: A ping is sent when the link was idle this long, seconds.
        link_timeout_s: A ping unanswered this long means the link is dead, seconds.
        close_timeout_s: Time allowed for the closing handshake on stop, seconds.
        max_receive_frame_bytes: Largest frame accepted from the server (bytes).
        reassembly_max_bytes: Bytes of incomplete fragmented messages kept (bytes).
        reassembly_timeout_s: An incomplete fragmented message is dropped after this.
        dedupe_window: How many recent no_drop frames per topic are remembered to drop
            resends (at most 4096).
        send_batch_bytes: Frames are handed to the transport in batches up to this size
            (bytes); a batch also ends where an ack point (ping) is due.
        write_limit_bytes: High-water mark of the transport's write buffer (bytes): a
            write waits above it. Small enough that data waits in the scheduler (where it
            can be superseded), large enough that one batch does not stall on it.
        tune_malloc: Raise glibc's malloc thresholds when :meth:`RobotLink.run` starts
            (process-wide; see :mod:`fleetctl.client.memory`).
        bind_reminder_interval_s: While ``bind_address`` is on no interface (the tunnel is
            down), or the server cannot be reached for the same reason, the failed
            attempts are logged at DEBUG, with a WARNING reminder at most this often,
            seconds (the first one explains).
        path_poll_s: While an early dial is under way, or a dead path is redialled, how
            often the kernel's TCP state is read again, seconds. Otherwise it is read when
            the path could first be declared dead (data in flight) or right after a
            write that follows an idle spell: no periodic wake-ups (each cost the robot
            about 0.2 ms of CPU, 0.45 % of a core at 20 per second).
        takeover_backoff_s: After the server closed the session with 4409 (another
            client connected with the same ``robot_name``), the wait before connecting
            again, doubled at each takeover in a row up to 12 times this, seconds: two
            clients of one robot took the session from each other ten times a second.
        path_idle_poll_s: With nothing in flight, the longest wait between two reads (it
            is also how often the pong backstop is checked), seconds.
        dead_ack_gap_s: With data unacknowledged, no ACK for at least this long (and for
            ``dead_ack_rtts`` smoothed RTTs) means the path is dead, seconds.
        dead_ack_rtts: The same gap in smoothed RTTs (``tcpi_rtt``).
        stale_ack_gaps: With the path dead, no ACK for this many dead gaps means the old
            connection holds nothing worth delivering any more: it is reset (a TCP RST,
            its unacknowledged data discarded by the kernel) and the link reconnects at
            the outage's pace. Before that, an ACK makes the dead path a false alarm and
            the old connection carries on.
        deflate_max_message_bytes: Messages up to this size are sent with
            permessage-deflate when the server accepts it (:mod:`fleetctl.linkdeflate`);
            0 does not offer the extension (today's frames on the wire).
        slow_deflate: The link rates (on the wire) below which the robot deflates every
            message, fragments of large ones too (:mod:`fleetctl.client.slowdeflate`).
        publish_to_offer_s: For a message offered without its publish time (a
            middleware that gave no source timestamp, or a frame the node made itself),
            how long before its offer it counts as published, seconds: the
            robot's own intake (DDS delivery, the take, the encode) puts 0.5-2 ms
            between the two (a 6 KB scan's is the longer), so after an outage such a
            message is fresh only when offered this long after the path was proven
            alive (docs/recovery.md, "Nothing ahead of the activation").
        max_publish_age_s: A publish time (the middleware's source timestamp) more than
            this before its offer, or after it, is not believed (a publisher on another
            host whose clock is off): the offer then counts as above, seconds.
    """

    open_timeout_s: float = 5.0
    dial: DialSettings = field(default_factory=DialSettings)
    failover_after_s: float = 0.5
    keepalive_interval_s: float = 0.5
    link_timeout_s: float = 3.0
    close_timeout_s: float = 1.0
    max_receive_frame_bytes: int = 32 * 1024 * 1024
    reassembly_max_bytes: int = 64 * 1024 * 1024
    reassembly_timeout_s: float = 5.0
    dedupe_window: int = 100_000
    send_batch_bytes: int = 1024 * 1024
    write_limit_bytes: int = 1024 * 1024
    tune_malloc: bool = True
    bind_reminder_interval_s: float = 30.0
    takeover_backoff_s: float = 5.0
    path_poll_s: float = 0.05
    path_idle_poll_s: float = 0.5
    dead_ack_gap_s: float = 0.15
    dead_ack_rtts: float = 4.0
    stale_ack_gaps: float = 2.0
    deflate_max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    slow_deflate: SlowDeflateSettings = field(default_factory=SlowDeflateSettings)
    publish_to_offer_s: float = 0.002
    max_publish_age_s: float = 1.0
