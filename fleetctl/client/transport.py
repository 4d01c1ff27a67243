"""The robot's WebSocket link to the fleet server: connect, send by schedule, receive.

:class:`RobotLink` is a thin asyncio layer over the pure :class:`Scheduler`:

- connects (Bearer token on the upgrade when configured, optional source address),
  subscribes to every ``subscribe`` entry (``RobofleetSubscription`` frames), and
  reconnects with exponential backoff and jitter, resubscribing each time;
- names its server session after the robot (``X-Fleetctl-Session: <robot_name>``), so
  the server keeps its subscriptions and no_drop frames for it while it is away (and
  across server restarts); subscriptions the server reinstates that are no longer in the
  config are unsubscribed; :meth:`RobotLink.stop` unsubscribes everything, which ends
  the session;
- sends what the scheduler picks, and marks ack points with WebSocket pings: the server
  answers a ping only after reading every earlier frame, so its pong acknowledges them
  (Robofleet III-B, ``UPDATEBPCOUNTER``);
- watches the kernel's ACKs (Linux ``TCP_INFO``): data unacknowledged and no ACK for
  ``max(dead_ack_gap_s, dead_ack_rtts x srtt)`` means the path is dead (a congested but
  live link keeps ACKing); it then dials a new connection at once (racing SYNs, fast
  early in the outage) and keeps the old one until the new one connects: if the old one
  got an ACK meanwhile it was a false alarm and the new socket is closed unused, else the
  old connection is reset and the upgrade runs on the new socket; a path still silent
  after ``stale_ack_gaps`` gaps is reset without waiting for the new socket (what it
  holds is stale), and every reset is a TCP RST (``SO_LINGER`` 0), so no orphan socket
  delivers the old data when the path returns (issue 19, docs/recovery.md);
- declares the link dead when a ping stays unanswered for ``link_timeout_s`` (TCP alone can
  take minutes to notice a radio that went silent; the backstop where ``TCP_INFO`` is
  missing or the server's application hangs) and reconnects;
- on a new connection after an outage, drops the latest-only messages held through it
  (:meth:`Scheduler.drop_stale`): they were published while the path was dead, fresh
  ones are due within a period and would wait behind them;
- receives frames, reassembles fragments, drops duplicate no_drop frames (a resend after a
  reconnect, see below) and hands complete frames to ``on_frame``.
- a token the server refuses for too many failed logins from this address (429 with
  ``Retry-After`` at the upgrade, close 4429 ``login_throttled``;
  :mod:`.loginthrottle`) is not "cannot connect": explained once per spell, reminded,
  counted, and the next attempt waits at least the server's hint.

Threading: everything runs on one asyncio loop, except :meth:`RobotLink.admit` (any thread),
:meth:`RobotLink.offer_threadsafe` (any thread; hops onto the loop from others) and
:meth:`RobotLink.feedback` (any thread: reads counters).

Duplicates: a no_drop message sent but not acknowledged when the link died is sent again
(at-least-once). A resend is the same frame, so receivers drop a no_drop frame whose
``(seq, publish_time_ns)`` they saw recently on its topic (see :mod:`.receiver`): a second
sender, or a reloaded page whose ``seq`` restarts at 1, stamps other publish times and is
never mistaken for a resend.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import errno
import functools
import json
import logging
import math
import random
import socket
import ssl
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus, InvalidURI
from websockets.uri import parse_uri

from fleetctl.batched_connection import BatchedWritesConnection
from fleetctl.client.clockcheck import ClockCheck, clock_line
from fleetctl.client.config import ClientConfig
from fleetctl.client.dialer import DialTimeout, dial_first
from fleetctl.client.linktuning import LinkTuning
from fleetctl.client.loginthrottle import EXPLANATION, LoginThrottled, from_close, from_response
from fleetctl.client.memory import tune_malloc
from fleetctl.client.outagelog import OutageLog, Say, sampled
from fleetctl.client.receiver import Receiver
from fleetctl.client.scheduler import Scheduler, SchedulerConfig, TopicFeedback
from fleetctl.client.segmentfill import SegmentFill
from fleetctl.client.slowdeflate import SlowDeflateSettings, SlowLinkDeflate
from fleetctl.client.standby import STANDBY_HEADER, Standby, keep_mapping_alive
from fleetctl.client.tcppath import (
    AckStall,
    TcpInfo,
    read_send_mss,
    read_tcp_info,
    reset_transport,
)
from fleetctl.client.wakeup import Wakeup
from fleetctl.frame_sink import FrameSink
from fleetctl.linkdeflate import RobotDeflateFactory, SmallMessageDeflate
from fleetctl.wire.control import encode_subscription

logger = logging.getLogger("fleetctl.client.link")

SESSION_HEADER = "X-Fleetctl-Session"  # fleetctl.server.sessions.SESSION_HEADER
# Set (True) on the log records that explain a refused token (4401, 4403, too many failed
# logins): a caller that reports those itself (``fleetctl replay``, which stops at once)
# filters them out rather than print the link's "retrying" beside its own error.
REFUSAL_RECORD = "fleetctl_refusal"
_REFUSAL = {REFUSAL_RECORD: True}
# Set on the log records that explain a failed connection attempt: a caller that stops at
# its first failure and says why itself (``fleetctl replay`` before it ever connected)
# filters them out, as it does the refusals.
UNREACHABLE_RECORD = "fleetctl_unreachable"
_UNREACHABLE = {UNREACHABLE_RECORD: True}
# Set on the server's refusals of a topic (unauthorized_send, once per topic and
# connection), which ``stats()["refused_topics"]`` lists: ``fleetctl replay`` names them
# all in its one-line error instead.
REFUSED_TOPIC_RECORD = "fleetctl_refused_topic"
_REFUSED_TOPIC = {REFUSED_TOPIC_RECORD: True}
PATH_RTT_DIALS = 5  # the dials whose SYN round trips give the path's (RobotLink._path_rtt_s)
_MAX_REFUSED_TOPICS = 1024  # topics kept of the server's unauthorized_send errors

Clock = Callable[[], float]


class Dialed(NamedTuple):
    """A connected TCP socket and the replica it reaches.

    Attributes:
        sock: The socket the WebSocket upgrade runs on.
        replica: The replica's position in ``ClientConfig.server_urls``.
    """

    sock: socket.socket
    replica: int


class PathDead(Exception):
    """The old connection's path is dead and a new TCP connection is ready.

    Attributes:
        dialed: The connected socket the next WebSocket upgrade runs on.
    """

    def __init__(self, message: str, dialed: Dialed) -> None:
        super().__init__(message)
        self.dialed = dialed


# What to look at when bind_address is on no interface; fleet0 is the interface the bundle
# of `fleetctl export` sets up (docs/robot.md).
TUNNEL_HINT = "check `sudo wg show` and `systemctl status wg-quick@fleet0`"


@dataclass(frozen=True)
class LinkFeedback:
    """What a producer that adapts to the link reads (the video hook: bitrate, keyframes).

    Attributes:
        connects: Connections established so far; a new one means the server and the
            viewers may have missed what was in flight.
        topic: The topic's counters and the link rate (:class:`TopicFeedback`).
    """

    connects: int
    topic: TopicFeedback


class LinkDead(Exception):
    """No pong within ``link_timeout_s``: the connection is abandoned."""


class PathStale(Exception):
    """The path stayed dead past ``stale_ack_gaps`` (:meth:`AckStall.stale`): the
    connection is reset and the link reconnects at the outage's pace."""


@dataclass(frozen=True)
class _Ended:
    """How a connection's session ended.

    Attributes:
        acked: A pong came back on it (the link worked: backoff starts over).
        path_dead: It ended because its path went silent (:class:`PathDead`,
            :class:`LinkDead`): reconnect without a backoff, the dialer paces itself.
        ready: A connected socket for the next upgrade (from :class:`PathDead`).
    """

    acked: bool
    path_dead: bool = False
    ready: Dialed | None = None


class LinkConnection(FrameSink, BatchedWritesConnection, ClientConnection):
    """Client connection that writes a batch of binary frames in one transport write and
    takes complete binary frames in the read that brought them.

    ``send()`` costs a flow-control round through the event loop per frame; fragments
    make frames small and many, so the link hands the transport a batch instead (see
    :class:`~fleetctl.batched_connection.BatchedWritesConnection`, which the server's
    ``RelayConnection`` shares). Received binary frames go to the receiver from
    ``data_received`` (:class:`~fleetctl.frame_sink.FrameSink`), a loop round sooner than
    through ``recv()``.
    """


def scheduler_config_for(config: ClientConfig) -> SchedulerConfig:
    """The scheduler settings implied by a client config's ``limits``."""
    robofleet = config.limits.scheduler == "robofleet"
    return SchedulerConfig(
        max_fragment_bytes=config.limits.max_fragment_bytes,
        no_drop_queue_messages=config.limits.no_drop_queue_messages,
        fragments=not robofleet,
        fixed_window_messages=1 if robofleet else None,
        # Time-based ids keep a restarted client's fragments "newer" for reassemblers.
        first_message_id=time.time_ns() // 1000,
    )


def backoff_delay_s(attempt: int, min_s: float, max_s: float, rng: random.Random) -> float:
    """Reconnect delay: ``min_s x 2^attempt`` capped at ``max_s``, times U(0.5, 1) jitter.

    Jitter spreads a fleet's reconnects after a server restart.
    """
    base = min(max_s, min_s * (2.0 ** min(attempt, 30)))
    return base * rng.uniform(0.5, 1.0)


class RobotLink:
    """The robot's connection to the fleet server.

    Args:
        config: The validated client configuration.
        on_frame: Called on the loop thread with every complete (reassembled) binary
            frame from the server. Exceptions it raises are logged and counted.
        clock: Monotonic clock in seconds (injected for tests).
        wall_clock_ns: The wall clock in ns, which publish times are read on (injected
            for tests).
        scheduler_config: Overrides the scheduler settings derived from ``config``.
        tuning: Transport settings not in the config file.
    """

    def __init__(
        self,
        config: ClientConfig,
        *,
        on_frame: Callable[[bytes], None],
        clock: Clock = time.monotonic,
        wall_clock_ns: Callable[[], int] = time.time_ns,
        scheduler_config: SchedulerConfig | None = None,
        tuning: LinkTuning | None = None,
        ssl_context: ssl.SSLContext | None = None,
    ) -> None:
        self.config = config
        # For wss:// URLs; None: the system's CAs (websockets' default). A robot reaches
        # its server inside the tunnel, plain; `fleetctl replay` reaches a fleet's TLS
        # port, whose certificate is often the fleet's own (--ca-file).
        self._ssl_context = ssl_context
        tuning = tuning or LinkTuning()
        # The outage dial pace is the operator's trade-off (client.yaml limits): it wins.
        self.tuning = dataclasses.replace(tuning, dial=dataclasses.replace(
            tuning.dial, outage_stagger_s=config.limits.outage_dial_interval_s))
        self._on_frame = on_frame
        self._clock = clock
        self._wall_clock_ns = wall_clock_ns
        self._clock_check = ClockCheck()
        self._scheduler = Scheduler(scheduler_config or scheduler_config_for(config))
        self._rates = {p.remote_topic: p.rate_limit_hz for p in config.publish}
        now = clock()
        for spec in config.publish:
            self._scheduler.register_topic(spec.remote_topic, spec.priority, now)
        self._admit_lock = threading.Lock()
        self._rng = random.Random()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        with contextlib.suppress(RuntimeError):
            self._loop = asyncio.get_running_loop()
            self._loop_thread = threading.get_ident()
        self._wake = Wakeup()
        # Send rounds written in the caller's turn (see hold_wakes): the connection whose
        # send loop is idle now, and whether wakes are being held.
        self._idle_ws: LinkConnection | None = None
        self._holding_wakes = False
        self._held_wake = False
        # Set by each write while the watchdog waits for one (see _watchdog).
        self._wrote: asyncio.Event | None = None
        # The watchdog's dead-path rule and the socket it reads, told of every write.
        self._watch: tuple[AckStall, Any] | None = None
        self._stop = asyncio.Event()
        self._stopped = asyncio.Event()
        self._running = False
        self._ws: LinkConnection | None = None
        # The uplink deflate of the current connection (None: not negotiated), and what
        # it and the scheduler had counted at the last acknowledgement.
        self._deflate: SmallMessageDeflate | None = None
        self._slow_deflate = SlowLinkDeflate(
            tuning.slow_deflate if config.limits.deflate_on_slow_links
            else SlowDeflateSettings(on_below_Bps=0.0))
        self._counted_frame_bytes = 0
        self._counted_saved_bytes = 0
        # While deflating every message: fragments sized to fill whole TCP segments of
        # the current connection's socket.
        self._segment_fill = SegmentFill()
        self._link_socket: Any = None
        self._pings: dict[int, float] = {}  # token -> sent time (s), this connection only
        self._last_send_s = 0.0
        tune = self.tuning
        self._receiver = Receiver(
            clock, on_frame, reassembly_max_bytes=tune.reassembly_max_bytes,
            reassembly_timeout_s=tune.reassembly_timeout_s, dedupe_window=tune.dedupe_window)
        self._counters: Counter[str] = Counter()
        self._urls = config.server_urls
        self._url_index = 0  # the current replica: the next dial tries it first
        self._connected_index: int | None = None  # the replica of the last connection
        self._server_errors: Counter[str] = Counter()
        # Topics the server refused to take from us (its unauthorized_send, once per topic
        # and connection); bounded like the server's own memo of them.
        self._refused_topics: set[str] = set()
        self._last_close: str | None = None
        self._connect_error: BaseException | None = None
        self._identities: list[str] = []
        self._subscribed: set[str] = set()  # confirmed by the server on this connection
        self._acked_any = False  # a pong came back on the current connection
        # Pongs of the current connection that came before its welcome (ping tokens, in
        # order): acknowledgements only once the welcome comes (_on_pong).
        self._held_acks: list[int] = []
        self._welcomed = False  # the server welcomed the current connection
        # When the current outage began (clock seconds): the last ACK of a dead path or
        # the oldest unanswered ping; None while the link is up.
        self._outage_since_s: float | None = None
        # When the last dial connected and its SYN's round trip (clock seconds, s): the
        # path worked by then (see _session); the connect log says both (after an
        # outage, where the time goes).
        self._dialed: tuple[float, float] | None = None
        # The SYN round trips of the last PATH_RTT_DIALS dials (s): their minimum says how
        # far ahead of an expected message an outage's dial must leave for its answer to
        # come first (_path_rtt_s). The minimum: one SYN slowed by a busy host (2.9 ms
        # against 0.4-1.2 in a traced e2e run) would otherwise widen the next outage's
        # window before each publish threefold.
        self._syn_rtts: deque[float] = deque(maxlen=PATH_RTT_DIALS)
        # Since the last reconnect after an outage: a latest-only message published
        # before this (clock seconds) is stale even when its offer comes later.
        self._fresh_since_s: float | None = None
        # The idle second connection taken over after an outage (fleetctl.client.standby),
        # whether the server offered it (its upgrade response), and whether the connection
        # _open just returned is that standby, to be activated.
        self._standby: Standby | None = None
        if config.limits.standby_connection:
            self._standby = Standby(self._upgrade_standby, self._dial_standby,
                                    _unacked_segments,
                                    retry_min_s=max(1.0, config.limits.reconnect_min_s),
                                    retry_max_s=max(30.0, config.limits.reconnect_max_s))
        self._standby_offered = False
        # When the standby's activation was sent, until the session it starts begins;
        # None when the next session is not an activation.
        self._activated_s: float | None = None
        # While bind_address is on no interface: since when, the last WARNING, attempts.
        self._unbound = OutageLog(self.tuning.bind_reminder_interval_s)
        # The server not reachable; a new (url, reason) is explained at once.
        self._unreachable = OutageLog(self.tuning.bind_reminder_interval_s)
        self._takeovers = 0  # sessions in a row another client of this robot took over
        self._ended_by_takeover = False  # the last session was closed with 4409
        self._refused = OutageLog(self.tuning.bind_reminder_interval_s)  # 4401/4403 closes
        # Tokens refused unhashed, too many failed logins from this address (429 at the
        # upgrade, 4429 login_throttled): explained once a spell, which a welcome ends.
        self._throttled = OutageLog(self.tuning.bind_reminder_interval_s)
        self._throttle: LoginThrottled | None = None  # the last, until a welcome
        self._throttled_at_s: float | None = None  # when, until the next attempt starts
        self._throttle_waited_s: float | None = None  # from the last to the next attempt
        self._session_throttle: LoginThrottled | None = None  # the session ended so
        self._last_error_code: str | None = None  # of this connection's last error frame

    # -- the API used by the ROS node -----------------------------------------------------

    def admit(self, remote_topic: str) -> bool:
        """Algorithm 1 rate limit, checked before the caller spends CPU on encoding.

        Thread-safe. Topics not in ``config.publish`` have no limit.

        Returns:
            False when the message must be skipped (counted as ``rate_limited``).
        """
        rate = self._rates.get(remote_topic)
        if rate is None:
            return True
        with self._admit_lock:
            return self._scheduler.admit(remote_topic, rate, self._clock())

    def offer(self, remote_topic: str, frame: bytes, *, priority: float, no_drop: bool,
              keyframe: bool = False, published_ns: int = 0) -> None:
        """Queue an encoded frame for sending. Call on the loop thread.

        Args:
            remote_topic: The frame's topic (as in its metadata).
            frame: One complete wire frame.
            priority: Algorithm 2 weight (>= 0).
            no_drop: Reliable in-order (bounded FIFO, kept across reconnects) or latest-only.
            keyframe: A video keyframe: later frames of the topic never replace it.
            published_ns: When the message was published (the middleware's source
                timestamp, wall clock ns; 0: not known). After an outage it decides
                whether the message is stale (:meth:`_published_s`).
        """
        now_s = self._clock()
        published_s = self._published_s(now_s, published_ns)
        # Only a known publish time drops a message at its offer: an estimated one would
        # drop fresh messages offered just after the path came back.
        fresh_since_s = self._fresh_since_s if published_s is not None else None
        if published_s is None:
            published_s = now_s - self.tuning.publish_to_offer_s
        if not self._scheduler.offer(remote_topic, frame, now_s, priority=priority,
                                     no_drop=no_drop, keyframe=keyframe,
                                     published_s=published_s, fresh_since_s=fresh_since_s):
            n = self._scheduler.no_drop_overflow
            if sampled(n):
                bounds = self._scheduler.config
                logger.warning("no_drop queue full (%d messages or %d bytes): dropped a "
                               "message on %s (%d dropped so far)",
                               bounds.no_drop_queue_messages, bounds.no_drop_queue_bytes,
                               remote_topic, n)
        if self._holding_wakes:
            self._held_wake = True
            return
        self._wake.set()

    def _published_s(self, now_s: float, published_ns: int) -> float | None:
        """*published_ns* (wall clock) on the link's clock, or None when not known or not
        believable (older than ``max_publish_age_s``, or in the future)."""
        if published_ns <= 0:
            return None
        age_s = (self._wall_clock_ns() - published_ns) / 1e9
        if not 0.0 <= age_s <= self.tuning.max_publish_age_s:
            return None
        return now_s - age_s

    def hold_wakes(self) -> None:
        """Until :meth:`send_held`, frames offered do not wake the send loop. Call on
        the loop thread, around a run of offers (the loop-thread intake's take of one
        subscription's messages)."""
        self._holding_wakes = True

    def send_held(self) -> None:
        """End :meth:`hold_wakes`: what was offered meanwhile is written now, in the
        caller's turn, when the send loop is idle and the connection takes writes without
        waiting; otherwise the send loop is woken as usual.

        Why: a woken send loop runs in the event loop's next round, after whatever else
        is ready: on loopback that hop was 0.1-0.15 ms of a pose's 0.5 ms through the
        client (docs/client.md, "Writing in the intake's turn").
        """
        self._holding_wakes = False
        if not self._held_wake:
            return
        self._held_wake = False
        ws = self._idle_ws
        if ws is not None:
            try:
                if self._send_round(ws):
                    return  # written; the loop sleeps on (its timed wake still comes)
            except Exception:  # the loop's own round will meet the same state and end
                logger.exception("writing in the intake's turn failed; the send loop "
                                 "takes over")
        self._wake.set()

    def offer_threadsafe(
        self, remote_topic: str, frame: bytes, *, priority: float, no_drop: bool,
        keyframe: bool = False, published_ns: int = 0,
    ) -> None:
        """:meth:`offer` from any thread (e.g. an rclpy executor's).

        On the loop's own thread the frame is queued at once; from another it hops onto
        the loop (which wakes the loop's thread).

        Raises:
            RuntimeError: The link has no event loop yet (create it inside the loop or
                call after :meth:`run` started).
        """
        loop = self._loop
        if loop is None:
            raise RuntimeError("RobotLink has no event loop yet: create it inside the loop")
        if threading.get_ident() == self._loop_thread:
            self.offer(remote_topic, frame, priority=priority, no_drop=no_drop,
                       keyframe=keyframe, published_ns=published_ns)
            return
        loop.call_soon_threadsafe(
            functools.partial(self.offer, remote_topic, frame, priority=priority,
                              no_drop=no_drop, keyframe=keyframe,
                              published_ns=published_ns))

    @property
    def connects(self) -> int:
        """Connections established so far (any thread)."""
        return self._counters["connects"]

    def feedback(self, remote_topic: str) -> LinkFeedback:
        """The link rate, the connection count and *remote_topic*'s counters (any thread:
        see :meth:`Scheduler.topic_feedback`)."""
        topic = self._scheduler.topic_feedback(remote_topic)
        share = self._slow_deflate.wire_share()
        if share != 1.0:
            topic = dataclasses.replace(topic, wire_share=share)
        return LinkFeedback(self._counters["connects"], topic)

    async def run(self) -> None:
        """Connect and keep the link up until :meth:`stop`; reconnects on any failure."""
        if self.tuning.tune_malloc:
            tune_malloc()
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self._running = True
        attempt = 0
        ready: Dialed | None = None  # connected early by the watchdog
        try:
            while not self._stop.is_set():
                ws = await self._connect(attempt, ready)
                ready = None
                if ws is None:
                    attempt += 1
                    continue
                if self._counters["connects"] > 0:
                    self._counters["reconnects"] += 1
                self._counters["connects"] += 1
                ended = await self._session(ws)
                attempt = 0 if ended.acked else attempt + 1  # a pong: start backoff over
                ready = ended.ready
                if self._ended_by_takeover and not self._stop.is_set():
                    await self._wait_stop(self._taken_over())
                    continue
                self._takeovers = 0
                # After a dead path the dialer paces itself (and a socket may be ready):
                # a backoff would only delay the first SYN after the link returns.
                if not self._stop.is_set() and not ended.path_dead:
                    delay = self._backoff(attempt)
                    throttle, self._session_throttle = self._session_throttle, None
                    if throttle is not None:
                        delay = self._throttled_wait_s(throttle, delay)
                    await self._wait_stop(delay)
        finally:
            if ready is not None:
                ready.sock.close()  # stopped before the upgrade ran on it
            if self._standby is not None:
                await self._standby.close()
            self._running = False
            self._stopped.set()

    def _taken_over(self) -> float:
        """The session went to a newer connection of the same ``robot_name`` (4409): not
        this process's (it abandons its own old connections first), so another client of
        this robot. Say so, and wait longer at each takeover in a row before taking the
        session back (reconnecting at once made the two clients take it from each other
        ten times a second, each losing what was in flight)."""
        self._takeovers += 1
        base = self.tuning.takeover_backoff_s
        delay: float = min(base * 2.0 ** (self._takeovers - 1), 12 * base)
        delay *= self._rng.uniform(0.8, 1.0)
        logger.error("another client connected to %s as robot %s and took this session over "
                     "(%d time(s) in a row): is a second fleetctl client running with this "
                     "robot_name (the service and one started by hand, two robots with one "
                     "client.yaml)? connecting again in %.0f s", self.url,
                     self.config.robot_name, self._takeovers, delay)
        return delay

    async def stop(self) -> None:
        """Unsubscribe, close the connection, and return once :meth:`run` has returned."""
        self._stop.set()
        self._wake.set()
        if self._running:
            await self._stopped.wait()

    def stats(self) -> dict[str, Any]:
        """A JSON-able snapshot: per-topic sent/acked/dropped, no_drop overflow,
        reconnects, RTT, in-flight bytes and frames, window, receive counters."""
        snap: dict[str, Any] = self._scheduler.stats(self._clock())
        snap["connected"] = self._ws is not None
        snap["connects"] = self._counters["connects"]
        snap["reconnects"] = self._counters["reconnects"]
        snap["link_timeouts"] = self._counters["link_timeouts"]
        snap["dead_paths"] = self._counters["dead_paths"]
        snap["stale_paths"] = self._counters["stale_paths"]
        snap["false_alarms"] = self._counters["false_alarms"]
        snap["connect_failures"] = self._counters["connect_failures"]
        snap["login_throttled"] = self._counters["login_throttled"]
        snap["login_retry_after_s"] = (None if self._throttle is None
                                       else self._throttle.retry_after_s)
        snap["login_throttled_waited_s"] = self._throttle_waited_s
        snap["failovers"] = self._counters["failovers"]
        snap["server_url"] = self.url
        snap["session_resumes"] = self._counters["session_resumes"]
        snap["session_mailbox_frames"] = self._counters["session_mailbox_frames"]
        snap["last_close"] = self._last_close
        snap["server_errors"] = dict(self._server_errors)
        snap["refused_topics"] = sorted(self._refused_topics)
        snap["identities"] = list(self._identities)
        snap["subscribed"] = sorted(self._subscribed)
        snap["received"] = self._receiver.stats()
        snap["standby"] = None if self._standby is None else self._standby.stats()
        slow = self._slow_deflate
        snap["uplink_deflate"] = {
            "negotiated": self._deflate is not None, "all_messages": slow.active,
            "switches": slow.switches, "wire_share": round(slow.wire_share(), 4),
            "fragment_payload_bytes": self._fragment_shares()}
        return snap

    @property
    def login_throttle(self) -> LoginThrottled | None:
        """The server's last refusal of this client's token for too many failed logins
        from its address (429, 4429 ``login_throttled``); ``None`` when there was none
        since the last authenticated connection."""
        return self._throttle

    @property
    def connect_error(self) -> BaseException | None:
        """Why the last connection attempt failed (the exception: ``OSError``, an
        ``ssl.SSLError``, websockets' ``InvalidHandshake``, ...); ``None`` once one
        succeeded, and before any failed."""
        return self._connect_error

    @property
    def last_close(self) -> str | None:
        """How the last connection ended (``"4401 bad token"``, ``"link timeout"``, ...);
        None while no connection has ended."""
        return self._last_close

    @property
    def scheduler(self) -> Scheduler:
        """The scheduler (read-only use: tests and benchmarks)."""
        return self._scheduler

    # -- connection life cycle ------------------------------------------------------------

    def _backoff(self, attempt: int) -> float:
        lim = self.config.limits
        return backoff_delay_s(max(attempt - 1, 0), lim.reconnect_min_s, lim.reconnect_max_s,
                               self._rng)

    async def _wait_stop(self, timeout_s: float) -> None:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._stop.wait(), timeout_s)

    @property
    def url(self) -> str:
        """The replica in use, or the one the next connection tries first."""
        return self._urls[self._url_index]

    async def _dial(self) -> Dialed:
        """The raced TCP connect, at the stagger for the current outage's age; the
        current replica first, the others after ``failover_after_s``."""
        order = [(self._url_index + k) % len(self._urls) for k in range(len(self._urls))]
        since = self._outage_since_s
        age = math.inf if since is None else max(0.0, self._clock() - since)
        dialed = await self._race(order, age)
        # The path works by now (the winning SYN's answer came): what is published from
        # here on is fresh (_session). The SYN's RTT (the kernel's first sample) is logged.
        info = read_tcp_info(dialed.sock)
        self._dialed = (self._clock(), info.srtt_s if info is not None else 0.0)
        if info is not None:
            self._syn_rtts.append(info.srtt_s)
        return dialed

    async def _race(self, order: list[int], outage_age_s: float = math.inf) -> Dialed:
        """:func:`dial_first` to the replicas at the positions *order*, from
        ``bind_address`` when one is set."""
        targets = []
        for i in order:
            uri = parse_uri(self._urls[i])
            targets.append((uri.host, uri.port))
        local = (None if self.config.bind_address is None
                 else (self.config.bind_address, 0))
        won, sock = await dial_first(targets, self.tuning.open_timeout_s, self.tuning.dial,
                                     head_start_s=self.tuning.failover_after_s,
                                     local_addr=local, outage_age_s=outage_age_s,
                                     ahead=self._ahead_s if outage_age_s < math.inf
                                     and self.config.limits.dial_ahead_of_messages else None)
        return Dialed(sock, order[won])

    @property
    def _path_rtt_s(self) -> float:
        """The path's round trip as the last dials measured it (0 before the first)."""
        return min(self._syn_rtts, default=0.0)

    def _ahead_s(self) -> float:
        """When the dialer's next extra attempt should start, as the dialer takes it: the
        seconds to a message it should lead by ``ahead_s`` (it starts the attempt then,
        and no sooner than ``ahead_s`` after the last one).

        Why: a message published before the winning SYN's answer came is dropped as
        stale (:meth:`Scheduler.drop_stale`: nothing published while the path may have
        been dead is sent), so a restore in the ~10 ms between two evenly paced SYNs cost
        the message published there a whole period. So two attempts lead each expected
        publish: one by *far* and one by *near*. A restore between the far one and the
        publish costs the period unless the near one's answer comes before the publish;
        a restore between the near one and the publish is the window left (traced e2e
        runs: 3 losses in 30 trials with a single attempt 3 ms ahead, about the 9 % that
        3 ms in a 50 ms and a 100 ms period predict). *near* is ``ahead_s`` (1.5 ms: 1.5
        to 3 SYN round trips on the e2e link), or 1.5 of the path's SYN round trips
        when that is longer (a Wi-Fi or LTE path: the answer needs one); *far* is twice
        *near*, for a host too busy to start or answer the near one in time.
        """
        now = self._clock()
        spacing = self.tuning.dial.ahead_s
        near = max(spacing, 1.5 * self._path_rtt_s)
        far = 2.0 * near
        # The attempt just started covers what is published up to *near* from now (the
        # 50 us: a timer that fires on time puts the next publish exactly there).
        publish = self._scheduler.next_publish_after(now + near + 50e-6)
        target = publish - far if publish - far > now else publish - near
        return target - now + spacing

    def _use_replica(self, index: int) -> None:
        """Replica *index* connected: it is the current one from now on. A connection to
        another replica than the last one is a failover (logged, counted)."""
        last = self._connected_index
        if last is not None and index != last:
            logger.warning("failed over from %s to %s", self._urls[last], self._urls[index])
            self._counters["failovers"] += 1
        self._url_index = self._connected_index = index

    def _skip_replica(self, index: int) -> None:
        """Replica *index* answered TCP but its handshake failed: the next dial starts
        with the next one (a list of one stays put)."""
        if index == self._url_index and len(self._urls) > 1:
            self._url_index = (index + 1) % len(self._urls)

    def _extensions(self) -> list[RobotDeflateFactory] | None:
        limit = self.tuning.deflate_max_message_bytes
        return [RobotDeflateFactory(limit)] if limit > 0 else None

    async def _open(self, ready: Dialed | None = None) -> LinkConnection:
        """One connection attempt: raced TCP connect within ``open_timeout_s`` (or the
        *ready* socket the watchdog connected), then TLS and the upgrade within another
        ``open_timeout_s``. After an outage, the standby connection instead, when it is
        usable: the connected socket shows the path works again, and becomes the next
        standby (:mod:`fleetctl.client.standby`)."""
        sock, index = ready if ready is not None else await self._dial()
        if self._standby is not None and self._outage_since_s is not None:
            try:
                spare = await self._standby.activate(index)
            except BaseException:
                sock.close()  # stopped while the standby was handed over
                raise
            if spare is not None:
                assert isinstance(spare, LinkConnection)
                self._standby.adopt(sock, index)
                self._activated_s = self._clock()
                self._use_replica(index)
                return spare
        try:
            ws = await self._upgrade(sock, index, standby=False)
        except BaseException as exc:
            if not isinstance(exc, asyncio.CancelledError):
                self._skip_replica(index)
            raise
        self._use_replica(index)
        return ws

    async def _upgrade(self, sock: socket.socket, index: int, *,
                       standby: bool) -> LinkConnection:
        """TLS and the WebSocket upgrade on *sock* (connected to replica *index*) within
        ``open_timeout_s``; *standby* asks for a standby connection. The socket is closed
        when that fails."""
        headers = {SESSION_HEADER: self.config.robot_name}
        if standby:
            headers[STANDBY_HEADER] = "1"
        if self.config.token is not None:
            headers["Authorization"] = f"Bearer {self.config.token}"
        tls: dict[str, Any] = {}
        if self._ssl_context is not None and self._urls[index].startswith("wss://"):
            tls["ssl"] = self._ssl_context  # websockets refuses one for ws://
        try:
            async with asyncio.timeout(self.tuning.open_timeout_s):
                ws = await connect(
                    self._urls[index], sock=sock, additional_headers=headers,
                    compression=None, extensions=self._extensions(), proxy=None,
                    open_timeout=None, ping_interval=None,
                    ping_timeout=None, close_timeout=self.tuning.close_timeout_s,
                    max_size=self.tuning.max_receive_frame_bytes,
                    write_limit=self.tuning.write_limit_bytes,
                    create_connection=LinkConnection, **tls)
        except BaseException:
            sock.close()  # the handshake failed or timed out: the socket is ours
            raise
        assert isinstance(ws, LinkConnection)
        return ws

    async def _upgrade_standby(self, sock: socket.socket, index: int) -> LinkConnection:
        keep_mapping_alive(sock)
        return await self._upgrade(sock, index, standby=True)

    async def _dial_standby(self) -> tuple[socket.socket, int]:
        """A socket for a standby: the current replica only, at the normal pace (the
        path works; this dial must not touch the outage state or the SYN timing)."""
        return await self._race([self._url_index])

    async def _connect(self, attempt: int,
                       ready: Dialed | None = None) -> LinkConnection | None:
        if self._throttled_at_s is not None:  # what the last refusal made us wait
            self._throttle_waited_s = self._clock() - self._throttled_at_s
            self._throttled_at_s = None
        connecting = asyncio.ensure_future(self._open(ready))
        stopper = asyncio.ensure_future(self._stop.wait())
        # stop() must not wait for a connection attempt to time out.
        await asyncio.wait({connecting, stopper}, return_when=asyncio.FIRST_COMPLETED)
        stopper.cancel()
        if not connecting.done():
            connecting.cancel()
            await asyncio.gather(connecting, return_exceptions=True)
            if ready is not None:
                ready.sock.close()  # cancelled before _open took it over
            return None
        try:
            ws = connecting.result()
            assert isinstance(ws, LinkConnection)
        except (OSError, TimeoutError, InvalidHandshake, InvalidURI) as exc:
            self._counters["connect_failures"] += 1
            self._connect_error = exc
            # Silence (no SYN-ACK, no refusal): the dialer paced its SYNs; go on at once.
            delay = 0.0 if isinstance(exc, DialTimeout) else self._backoff(attempt + 1)
            throttle = (from_response(exc.response.status_code, exc.response.headers,
                                      time.time())
                        if isinstance(exc, InvalidStatus) else None)
            if throttle is not None:  # the server answered: reachable, and bound
                self._log_bound_again()
                self._log_reachable_again()
                delay = self._throttled_wait_s(throttle, delay)
            elif isinstance(exc, OSError) and exc.errno == errno.EADDRNOTAVAIL:
                self._log_unbound(delay)
            else:
                self._log_bound_again()
                self._log_unreachable(self._failure_reason(exc), delay)
            await self._wait_stop(delay)
            return None
        self._log_bound_again()
        self._log_reachable_again()
        self._connect_error = None
        return ws

    def _check_wall_clock(self, ws: LinkConnection) -> None:
        """Compare this robot's wall clock with the server's Date (fleetctl.client.clockcheck):
        a robot hours off had its live data shown as hours old, and nothing here said so."""
        date = ws.response.headers.get("Date") if ws.response is not None else None
        said = self._clock_check.reading(date, self._wall_clock_ns() / 1e9)
        if said is not None:
            kind, offset_s = said
            logger.log(logging.WARNING if kind == "off" else logging.INFO, "%s",
                       clock_line(kind, offset_s, self.url))

    def _failure_reason(self, exc: BaseException) -> str:
        """Why a connect failed, in words: a bare ``TimeoutError`` was all a robot's log said
        of a port that accepted TCP and never answered the upgrade."""
        if type(exc) is TimeoutError and not str(exc):  # open_timeout_s, after the dial
            return (f"the connection was accepted but the WebSocket handshake got no answer in "
                    f"{self.tuning.open_timeout_s:g} s (a stalled relay, or something "
                    "else listens on that port)")
        return str(exc) or type(exc).__name__

    def _log_unreachable(self, reason: str, delay_s: float) -> None:
        """Log a connect that failed (refused, timed out, a failed upgrade): explain once
        per outage and reason, then remind every ``bind_reminder_interval_s``; the
        attempts in between go to DEBUG. A robot started before its server (or through a
        long server outage) logged a WARNING every few seconds for as long as it lasted.
        The token is never logged: only the URL and the reason."""
        outage = self._unreachable
        now = self._clock()
        say = outage.failed(now, (self.url, reason))
        if say is Say.EXPLAIN:
            logger.warning("cannot connect to %s: %s; retrying every %g s or less, quietly "
                           "(a reminder every %g s)", self.url, reason,
                           self.config.limits.reconnect_max_s,
                           self.tuning.bind_reminder_interval_s, extra=_UNREACHABLE)
        elif say is Say.REMIND:
            assert outage.since_s is not None
            logger.warning("still cannot connect to %s after %.0f s (%d attempts): %s",
                           self.url, now - outage.since_s, outage.attempts, reason,
                           extra=_UNREACHABLE)
        else:
            logger.debug("cannot connect to %s: %s; retrying in %.2f s", self.url, reason,
                         delay_s)

    def _log_reachable_again(self) -> None:
        """End an outage of the server (a connection was opened), if one ran."""
        ended = self._unreachable.ended(self._clock())
        if ended is not None:
            logger.info("reached %s after %.0f s (%d attempts failed)", self.url, *ended)

    def _throttled_wait_s(self, throttle: LoginThrottled, backoff_s: float) -> float:
        """The server refused this client's token unhashed: too many failed logins from
        its address. Count and log it; return the wait before the next attempt: at least
        the server's hint times U(1, 1.2) (robots behind one NAT do not come back in
        lockstep) and at least *backoff_s* (the normal backoff, alone when there is no
        hint). Sooner would only be refused again: the relay's budget refills one
        failure at a time (2 s), and the hint says when."""
        self._counters["login_throttled"] += 1
        self._throttle = throttle
        self._throttled_at_s = self._clock()
        delay = backoff_s
        if throttle.retry_after_s is not None:
            delay = max(delay, throttle.retry_after_s * self._rng.uniform(1.0, 1.2))
        self._log_throttled(throttle, delay)
        return delay

    def _log_throttled(self, throttle: LoginThrottled, delay_s: float) -> None:
        """Explain a throttled spell once (the server is reachable; what to check), then
        remind every ``bind_reminder_interval_s``; the attempts in between go to DEBUG.
        The token is never logged."""
        outage = self._throttled
        now = self._clock()
        hint = ("the server's Retry-After" if throttle.where == "upgrade"
                else "the server's close reason")
        if throttle.retry_after_s is None:
            hint = "the server gave no usable hint: the normal backoff"
        say = outage.failed(now, self.url)
        if say is Say.EXPLAIN:
            logger.error(
                "%s is reachable but refuses this robot's token for now (%s, %s): %s; check "
                "token_file (%s's token from fleetctl add-robot; a wrong one also gets "
                "4401 closes) and the other clients behind this robot's address; next "
                "try in %.1f s (%s), a reminder every %g s", self.url,
                "HTTP 429" if throttle.where == "upgrade" else "close 4429",
                throttle.retry_text(), EXPLANATION, self.config.robot_name, delay_s, hint,
                self.tuning.bind_reminder_interval_s, extra=_REFUSAL)
        elif say is Say.REMIND:
            assert outage.since_s is not None
            logger.error("%s still refuses this robot's token after %.0f s (%d attempts "
                         "refused): %s; next try in %.1f s", self.url, now - outage.since_s,
                         outage.attempts, EXPLANATION, delay_s, extra=_REFUSAL)
        else:
            logger.debug("%s refused the token unhashed (too many failed logins from this "
                         "address); next try in %.2f s", self.url, delay_s)

    def _log_unbound(self, delay_s: float) -> None:
        """Log a connect that failed with EADDRNOTAVAIL: ``bind_address`` is on no
        interface, i.e. the WireGuard tunnel is down. Explain once per outage, then remind
        every ``bind_reminder_interval_s``; the attempts in between go to DEBUG."""
        outage = self._unbound
        now = self._clock()
        address = self.config.bind_address
        say = outage.failed(now, "unbound")  # one reason: explained once per outage
        if say is Say.EXPLAIN:
            logger.warning(
                "cannot bind %s (bind_address in the client config): it is on no interface: "
                "the WireGuard tunnel is down? %s; retrying every %.0f s or less, quietly",
                address, TUNNEL_HINT, self.config.limits.reconnect_max_s)
        elif say is Say.REMIND:
            assert outage.since_s is not None
            logger.warning("still cannot bind %s: the tunnel has been down for %.0f s "
                           "(%d attempts); %s", address, now - outage.since_s,
                           outage.attempts, TUNNEL_HINT)
        else:
            logger.debug("cannot bind %s (tunnel down); retrying in %.2f s", address, delay_s)

    def _log_bound_again(self) -> None:
        """End an outage of ``bind_address`` (it is on an interface again), if one ran."""
        ended = self._unbound.ended(self._clock())
        if ended is not None:
            logger.info("%s is on an interface again after %.0f s (%d attempts failed)",
                        self.config.bind_address, *ended)

    async def _session(self, ws: LinkConnection) -> _Ended:
        """Run one connection until it fails or stop()."""
        self._ws = ws
        self._use_deflate(ws)
        self._pings.clear()
        self._subscribed.clear()
        self._identities = []
        self._acked_any = False
        self._held_acks = []
        self._welcomed = False
        self._last_error_code = None
        activated_s, self._activated_s = self._activated_s, None
        activating = activated_s is not None
        if not activating:
            # An older server, or another Robofleet-convention one, does not offer it.
            # The fleetctl relay offers it on every upgrade, and welcomes (again, on an
            # activation) every connection it accepts: there, acknowledgements wait for
            # the welcome (_on_pong).
            self._standby_offered = ws.response is not None and (
                ws.response.headers.get(STANDBY_HEADER) == "1")
        dialed, self._dialed = self._dialed, None
        # While the server refuses this robot (4401/4403, until a welcome) each retry's
        # connect was an INFO line: every 5 s for as long as a token stayed wrong, around
        # the one ERROR and its 30 s reminders that say what to do.
        level = logging.DEBUG if self._refused.since_s is not None else logging.INFO
        if dialed is None:
            self._drop_stale(None)
            logger.log(level, "connected to %s", self.url)
        else:
            dialed_s, syn_rtt_s = dialed
            # What was published before the dial returned, after the winning SYN's answer
            # came, is stale. Only that is proof: the path came back somewhere between
            # the SYN's send and its answer, and a SYN can wait on the robot's own host
            # before it leaves (a userspace WireGuard on a busy CPU: e2e ``peer`` saw a
            # 4.5 ms SYN round trip against 0.5 ms, and a scan published 1.5 ms before
            # that SYN was sent was delivered, stale). The message expected next is still
            # kept: the dialer sends a SYN ``ahead_s`` before it.
            self._drop_stale(dialed_s)
            # The upgrade includes a wait for the old connection when the watchdog dialled
            # early (a false alarm is decided first).
            ready_s = activated_s if activated_s is not None else self._clock()
            logger.log(level, "connected to %s (SYN round trip %.1f ms, %s %.1f ms)", self.url,
                       syn_rtt_s * 1e3, "standby activated in" if activating else "upgrade",
                       (ready_s - dialed_s) * 1e3)
        if not activating:  # a standby's upgrade answer may be minutes old
            self._check_wall_clock(ws)
        tasks: list[asyncio.Task[None]] = []
        ended = _Ended(acked=False)
        self._ended_by_takeover = False
        ws.frame_sink = self._sink
        try:
            # When activating, {"type": "activate"} went first (Standby.activate): the
            # server moves the session here, then come the subscriptions and the frames.
            await self._subscribe_all(ws, subscribe=True)
            tasks = [asyncio.create_task(self._send_loop(ws)),
                     asyncio.create_task(self._receive_loop(ws)),
                     asyncio.create_task(self._watchdog(ws))]
            stop = asyncio.create_task(self._stop.wait())
            done, _ = await asyncio.wait([*tasks, stop], return_when=asyncio.FIRST_COMPLETED)
            stop.cancel()
            logged: BaseException | None = None
            for task in done:
                if task is stop or task.cancelled():
                    continue
                # A clean close (1000/1001, e.g. a server restart) ends the receive loop
                # without an exception: report it like the others, once (the send and
                # receive loops both ending with one close logged it twice).
                exc = task.exception()
                end = exc or _close_exc(ws)
                if not (isinstance(end, ConnectionClosed) and isinstance(logged, ConnectionClosed)):
                    self._log_session_end(end)
                    logged = end
                if isinstance(exc, (LinkDead, PathDead, PathStale)):
                    ended = _Ended(False, True, exc.dialed if isinstance(exc, PathDead) else None)
            if self._stop.is_set():
                await self._goodbye(ws)
        except ConnectionClosed as exc:
            self._log_session_end(exc)
            if activating and not self._acked_any:
                # The standby was gone (a server restarted during the outage): dial again
                # at once, as after any dead path.
                ended = _Ended(False, True)
        finally:
            if self._standby is not None:
                self._standby.main_down()
            ws.frame_sink = None  # what the old connection still reads is not delivered
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            self._ws = None
            self._scheduler.on_disconnect(self._clock())
            self._receiver.on_disconnect()
            if ended.path_dead:  # a reset: the old path must not deliver stale data later
                reset_transport(ws.transport)
            else:
                ws.transport.abort()
        return _Ended(self._acked_any, ended.path_dead, ended.ready)

    def _drop_stale(self, alive_since_s: float | None) -> None:
        """A connection opened: drop held latest-only messages that are stale by now
        (:meth:`Scheduler.drop_stale`; *alive_since_s*: from when the path is proven to
        work, None if not known), and after an outage, those offered later but published
        before *alive_since_s*; the outage, if one ran, is over."""
        outage = self._outage_since_s is not None
        self._outage_since_s = None
        if outage:
            self._fresh_since_s = alive_since_s
        dropped = self._scheduler.drop_stale(self._clock(), after_outage=outage,
                                             alive_since_s=alive_since_s)
        if dropped:
            logger.info("dropped %d held latest-only messages: stale after the outage",
                        dropped)

    def _log_refused(self, code: int) -> None:
        """The server refused this client's identity (4401 bad token, 4403 no identity):
        explain once with what to check, then remind every ``bind_reminder_interval_s``
        (the auth map reloads live, so the link keeps retrying; three lines per attempt
        were logged before)."""
        if self._refused.failed(self._clock(), code) is Say.QUIET:
            logger.debug("connection to %s closed: %s", self.url, self._last_close)
            return
        hint = (f"the server knows no such token: check token_file ({self.config.robot_name}'s "
                "token from fleetctl add-robot) against the server's auth map"
                if code == 4401 else
                "no identity of the server's auth map matches this client's token or source "
                "address (bind_address): add one, or fix those")
        logger.error("connection to %s closed: %s: %s; retrying every %g s or less "
                     "(the server reloads its auth map live), a reminder every %g s",
                     self.url, self._last_close, hint, self.config.limits.reconnect_max_s,
                     self.tuning.bind_reminder_interval_s, extra=_REFUSAL)

    def _log_session_end(self, exc: BaseException | None) -> None:
        if isinstance(exc, ConnectionClosed):
            rcvd = exc.rcvd
            self._last_close = (f"{rcvd.code} {rcvd.reason}".strip() if rcvd is not None
                                else "no close frame")
            self._ended_by_takeover = rcvd is not None and rcvd.code == 4409
            throttle = (None if rcvd is None
                        else from_close(rcvd.code, rcvd.reason, self._last_error_code))
            if throttle is not None:  # logged with the wait, when run() knows it
                self._session_throttle = throttle
            elif rcvd is not None and rcvd.code in (4401, 4403):
                self._log_refused(rcvd.code)
            else:
                logger.warning("connection to %s closed: %s", self.url, self._last_close)
        elif isinstance(exc, LinkDead):
            self._counters["link_timeouts"] += 1
            self._last_close = "link timeout"
            logger.warning("%s", exc)
        elif isinstance(exc, PathDead):
            self._counters["dead_paths"] += 1
            self._last_close = "dead path"
            logger.warning("%s", exc)
        elif isinstance(exc, PathStale):
            self._counters["stale_paths"] += 1
            self._last_close = "stale path"
            logger.warning("%s", exc)
        elif exc is not None:
            self._last_close = f"error: {exc!r}"
            logger.error("link to %s failed: %r", self.url, exc)

    async def _subscribe_all(self, ws: ClientConnection, *, subscribe: bool) -> None:
        for spec in self.config.subscribe:
            await ws.send(encode_subscription(spec.remote_topic, subscribe))

    async def _goodbye(self, ws: ClientConnection) -> None:
        try:
            async with asyncio.timeout(self.tuning.close_timeout_s):
                await self._subscribe_all(ws, subscribe=False)
                await ws.close()
        except (TimeoutError, ConnectionClosed, OSError) as exc:
            logger.info("closing handshake did not complete: %r", exc)

    # -- sending --------------------------------------------------------------------------

    async def _send_loop(self, ws: LinkConnection) -> None:
        while True:
            self._wake.clear()
            if not self._send_round(ws):
                # The transport is above its write limit, or the connection is closing:
                # send_context waits for the drain (or raises ConnectionClosed).
                async with ws.send_context():
                    pass
                continue
            idle_left = self.tuning.keepalive_interval_s - (self._clock() - self._last_send_s)
            self._idle_ws = ws
            try:
                await self._wake.wait(max(idle_left, 0.01))
            finally:
                self._idle_ws = None

    def _send_round(self, ws: LinkConnection) -> bool:
        """Write what the scheduler releases now, in batches, each with its ack point as
        due; False, having stopped before taking another frame, when the connection
        cannot take a write without waiting (the caller waits, then calls again)."""
        sched = self._scheduler
        clock = self._clock
        batch_limit = self.tuning.send_batch_bytes
        if not ws.can_write_now():
            return False
        now = clock()
        batch: list[bytes] = []
        size = 0
        while (frame := sched.next_frame(now)) is not None:
            batch.append(frame)
            size += len(frame)
            due = sched.ack_due()
            if due or size >= batch_limit:
                self._send(ws, batch, now, ping=due)
                batch, size = [], 0
                if not ws.can_write_now():
                    return False
                now = clock()
        if batch:
            # next_frame said no (queue empty or window full): only a pong can help
            # now, so the batch goes with a ping.
            self._send(ws, batch, now, ping=True)
        elif sched.has_unpinged():
            self._send(ws, [], now, ping=True)
        elif not self._pings and now - self._last_send_s >= self.tuning.keepalive_interval_s:
            self._send(ws, [], now, ping=True)  # keepalive: proves the link
        return True

    def _send(self, ws: LinkConnection, batch: list[bytes], now_s: float, *,
              ping: bool) -> None:
        """Write *batch*, and with *ping* an ack point after it, in one transport write
        (the caller checked ``ws.can_write_now()``)."""
        if self._wrote is not None:
            self._wrote.set()  # the watchdog looks at the ACKs of what this writes
        if not ping:
            ws.write_frames_now(batch)
            self._last_send_s = self._clock()
            self._note_sent()
            return
        token = self._scheduler.ack_point(now_s)
        self._pings[token] = now_s
        waiter = ws.write_frames_now(batch, ping=token.to_bytes(8, "big"))
        self._last_send_s = self._clock()
        self._note_sent()
        assert waiter is not None
        waiter.add_done_callback(functools.partial(self._on_pong, token))

    def _note_sent(self) -> None:
        """Tell the watchdog's :class:`AckStall` what the write just sent and when (one
        ``TCP_INFO`` read, 2 µs of syscall and ~8 µs in all on this host under load, no
        wake-up), while it watches data in flight: data written after the last ACK is then
        not taken for data unanswered since the watch began, nor data sent into a cut for
        data sent later."""
        watch = self._watch
        if watch is not None and watch[0].watching:
            stall, sock = watch
            stall.sent(self._last_send_s, read_tcp_info(sock))

    def _fragment_shares(self) -> dict[str, int | None]:
        """Each topic's fragment share of its message now, for the stats: what the
        segment fill gives the topics it has seen, while it is in use."""
        sizer = self._scheduler.fragment_sizer
        return {} if sizer is None else {t: sizer(t) for t in self._segment_fill.topics()}

    def _use_deflate(self, ws: LinkConnection) -> None:
        """Take *ws*'s uplink deflate (if the relay accepted it), set as the link is."""
        found = [ext for ext in ws.protocol.extensions
                 if isinstance(ext, SmallMessageDeflate)]
        self._deflate = found[0] if found else None
        self._counted_frame_bytes = self._scheduler.sent_bytes_total
        self._counted_saved_bytes = 0
        self._link_socket = ws.transport.get_extra_info("socket")
        self._slow_deflate.new_connection()
        if self._deflate is not None:
            self._deflate.deflate_all = self._slow_deflate.active
            self._deflate.fragment_observer = self._segment_fill
        self._size_fragments()

    def _size_fragments(self) -> None:
        """While every message is deflated, give each topic's fragments the share of
        their message that fills whole TCP segments (:mod:`fleetctl.client.segmentfill`)
        at the link's MSS and rate now; otherwise the scheduler's own size."""
        scheduler = self._scheduler
        if self._deflate is None or not self._deflate.deflate_all:
            scheduler.fragment_sizer = None
            return
        budget = (scheduler.link_rate_Bps * self._slow_deflate.wire_share()
                  * scheduler.config.fragment_time_s)
        scheduler.fragment_sizer = functools.partial(
            self._segment_fill.payload_bytes, mss=read_send_mss(self._link_socket),
            budget_wire_bytes=budget, max_fragment_bytes=scheduler.config.max_fragment_bytes)

    def _decide_deflate(self, deflate: SmallMessageDeflate) -> None:
        """On an acknowledgement (the scheduler's rate may have moved): deflate every
        message or only small ones, by the link's rate on the wire
        (:mod:`fleetctl.client.slowdeflate`)."""
        sent, saved = self._scheduler.sent_bytes_total, deflate.saved_bytes
        self._slow_deflate.observe(sent - self._counted_frame_bytes,
                                   saved - self._counted_saved_bytes)
        self._counted_frame_bytes, self._counted_saved_bytes = sent, saved
        slow = self._slow_deflate
        share, was_on = slow.wire_share(), slow.active
        rate = self._scheduler.link_rate_Bps
        deflate.deflate_all = slow.decide(rate, self._clock())
        if deflate.deflate_all != was_on:
            if not deflate.deflate_all:
                # The rates were measured in deflated bytes: what a byte sent raw
                # now costs (small messages stay deflated, so this errs small).
                self._scheduler.rescale_rates(share)
            if sampled(slow.switches):
                logger.info("uplink at %.1f Mbit/s on the wire: %s (switch %d)",
                            rate * share * 8e-6,
                            "deflating every message, fragments of large ones too"
                            if deflate.deflate_all else "deflating small messages only",
                            slow.switches)
        self._size_fragments()

    def _on_pong(self, token: int, fut: asyncio.Future[float]) -> None:
        if self._pings.pop(token, None) is None or fut.cancelled() or fut.exception():
            return
        if self._standby_offered and not self._welcomed:
            # A relay refusing this robot's token (4401, 4429) drops what it sent, but
            # its WebSocket protocol still answers the ping after it, sometimes before
            # the close: taken as an acknowledgement, those no_drop frames were lost
            # (benchmarks/soak_client.py). A pong before the welcome waits for it.
            self._held_acks.append(token)
            return
        self._acknowledged(token)

    def _acknowledged(self, token: int) -> None:
        """The server has everything sent before the ping *token*."""
        if not self._acked_any:
            self._acked_any = True
            if self._standby is not None:  # the path works: keep a standby beside it
                self._standby.main_up(self._standby_offered)
        self._scheduler.on_ack(token, self._clock())
        if self._deflate is not None:
            self._decide_deflate(self._deflate)
        # A pong matters to the send loop only when something waits for the window it
        # opened; otherwise waking it costs a loop round per message for nothing.
        if self._scheduler.has_sendable():
            self._wake.set()

    async def _watchdog(self, ws: ClientConnection) -> None:
        """Watch the connection's health; raise :class:`PathDead` or :class:`LinkDead`.

        The kernel's ACK state is read (:class:`AckStall`) after a write that follows an
        idle spell, and then when the data in flight could first count as dead; no
        periodic polling while the link works. When the path looks dead, a new TCP
        connection is dialled at once while this one carries on; once it connects, this
        one is abandoned unless an ACK came meanwhile (a false alarm: the new socket is
        closed before the upgrade, so the server's session is not taken over). The pong
        timeout stays as the backstop.
        """
        tune = self.tuning
        sock = ws.transport.get_extra_info("socket")
        stall = AckStall(tune.dead_ack_gap_s, tune.dead_ack_rtts, tune.stale_ack_gaps)
        self._watch = (stall, sock)
        redial: asyncio.Task[Dialed] | None = None
        wrote = self._wrote = asyncio.Event()
        planned: float | None = None  # when this task asked to wake, for the log
        try:
            while True:
                now = self._clock()
                info = read_tcp_info(sock)
                wrote.clear()  # no await since the read: a later write sets it again
                dead = info is not None and stall.dead(now, info)
                if dead and redial is None and info is not None:
                    late_s = None if planned is None else now - planned
                    redial = self._start_redial(now, info, stall, late_s)
                planned = None
                if redial is not None and redial.done():
                    done, redial = redial, None  # PathDead hands its socket on
                    redial = self._redial_done(done, dead, info)
                # After the switch above: a new socket that connected is used, not dropped.
                if dead and info is not None and stall.stale(now, info):
                    raise PathStale(
                        f"no ACK from {self.url} for {info.last_ack_s:.2f} s: resetting the "
                        "connection (what it holds is stale), reconnecting")
                self._check_pongs(now)
                if redial is not None and not redial.done():
                    # the new connection is used the moment it connects
                    await asyncio.wait({redial}, timeout=tune.path_poll_s)
                    continue
                due = None if info is None else stall.next_check_s(now, info)
                if due is None:  # nothing in flight: until the next write
                    # asyncio.timeout, not wait_for: no task per wait (this runs per write)
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(tune.path_idle_poll_s):
                            await wrote.wait()
                else:  # when it could be dead; at the outage's pace once it is
                    wait_s = due if due > 0 else tune.path_poll_s
                    planned = now + wait_s
                    await asyncio.sleep(wait_s)
        finally:
            self._wrote = self._watch = None
            if redial is not None:
                await _discard(redial)

    def _start_redial(self, now_s: float, info: TcpInfo, stall: AckStall,
                      late_s: float | None) -> asyncio.Task[Dialed]:
        """The path looks dead: note when the outage began and dial a new connection.

        *late_s*: how much later than asked the watchdog woke for this reading (None: it
        was woken by a write), logged with the kernel's readings: a false alarm on a busy
        host is told from a cut by them."""
        if self._outage_since_s is None:
            self._outage_since_s = now_s - info.last_ack_s
        logger.warning("no ACK from %s for %.3f s with %d segments unacknowledged (dead "
                       "after %.3f s; srtt %.1f ms, rttvar %.1f ms, in flight for %.3f s, "
                       "watchdog %s): dialing a new connection, keeping this one until it "
                       "connects", self.url, info.last_ack_s, info.unacked,
                       stall.gap_s(info), info.srtt_s * 1e3, info.rttvar_s * 1e3,
                       stall.in_flight_s(now_s),
                       "woken by a write" if late_s is None else f"{late_s * 1e3:.1f} ms late")
        return asyncio.create_task(self._dial())

    def _redial_done(self, redial: asyncio.Task[Dialed], dead: bool,
                     info: TcpInfo | None) -> asyncio.Task[Dialed] | None:
        """The early dial ended: switch to its socket, or drop it (false alarm, failure).

        Raises:
            PathDead: The new socket connected and the old path is still silent.
        """
        if redial.cancelled():
            return None
        exc = redial.exception()
        if isinstance(exc, DialTimeout):
            return None  # still silent: the next poll dials again (at the outage's pace)
        if exc is not None:
            # Refused or unreachable: the server is reachable and said no; the pong
            # timeout and the normal reconnect with backoff take it from here.
            logger.info("early dial failed: %r", exc)
            return redial  # kept done: no new early dial on this connection
        new = redial.result()
        if dead:
            silent = "" if info is None else (
                f" (no ACK for {info.last_ack_s:.3f} s, {info.unacked} segments "
                "unacknowledged)")
            raise PathDead(f"path to {self.url} dead{silent}: switching to the new "
                           f"connection to {self._urls[new.replica]}", new)
        new.sock.close()
        self._outage_since_s = None
        self._counters["false_alarms"] += 1
        logger.info("the old connection got an ACK again: false alarm, new socket closed")
        return None

    def _check_pongs(self, now_s: float) -> None:
        """The backstop: a ping unanswered for ``link_timeout_s``."""
        oldest = min(self._pings.values(), default=None)
        if oldest is not None and now_s - oldest > self.tuning.link_timeout_s:
            if self._outage_since_s is None:
                self._outage_since_s = oldest
            raise LinkDead(f"no pong from {self.url} for "
                           f"{self.tuning.link_timeout_s:.1f} s: reconnecting")

    # -- receiving ------------------------------------------------------------------------

    def _sink(self, frame: bytes) -> bool:
        """A binary frame, in the read that brought it (``LinkConnection.frame_sink``)."""
        self._receiver.on_binary(frame)
        return True

    async def _receive_loop(self, ws: LinkConnection) -> None:
        """Text frames, and binary frames that queued behind one (the sink takes the rest)."""
        async for message in ws:
            if isinstance(message, str):
                stale_patterns = self._on_text(message)
                ws.message_handled()
                for stale in stale_patterns:
                    await ws.send(encode_subscription(stale, False))
            else:
                self._receiver.on_binary(message)
                ws.message_handled()

    def _welcome_acks(self) -> None:
        """The server accepted this connection: the pongs held until now acknowledge."""
        self._welcomed = True
        held, self._held_acks = self._held_acks, []
        for token in held:
            self._acknowledged(token)

    def _on_text(self, text: str) -> list[str]:
        """Handle a server text frame; return subscriptions to drop (stale in the session)."""
        try:
            event = json.loads(text)
        except ValueError:
            logger.warning("server sent text that is not JSON: %.200r", text)
            return []
        kind = event.get("type") if isinstance(event, dict) else None
        if kind == "session":
            return self._on_session(event)
        if kind == "welcome":
            self._identities = [str(i) for i in event.get("identities", [])]
            logger.info("authenticated as %s", ", ".join(self._identities) or "(nobody)")
            self._refused.ended(self._clock())  # a later refusal is explained again
            self._end_throttled()
            self._welcome_acks()
        elif kind in ("subscribed", "unsubscribed"):
            pattern = str(event.get("topic_regex"))
            if kind == "subscribed":
                self._subscribed.add(pattern)
            else:
                self._subscribed.discard(pattern)
        elif kind == "error":
            code = str(event.get("code"))
            self._server_errors[code] += 1
            self._last_error_code = code
            topic = event.get("topic")
            if (code == "unauthorized_send" and isinstance(topic, str)
                    and len(self._refused_topics) < _MAX_REFUSED_TOPICS):
                self._refused_topics.add(topic)
            if code in ("bad_token", "login_throttled"):  # the close that follows says it
                logger.debug("server error bad_token: %s", event.get("message"))
            elif isinstance(topic, str):
                logger.warning("server error %s on %s: %s", code, topic, event.get("message"),
                               extra=_REFUSED_TOPIC if code == "unauthorized_send" else None)
            else:  # "on None" was printed for errors about no topic
                logger.warning("server error %s: %s", code, event.get("message"))
        else:
            logger.debug("server: %.200s", text)
        return []

    def _end_throttled(self) -> None:
        """Authenticated: a throttled spell, if one ran, is over."""
        self._throttle = None
        ended = self._throttled.ended(self._clock())
        if ended is not None:
            logger.info("%s takes this robot's token again after %.0f s (%d attempts "
                        "refused for too many failed logins from this address)", self.url,
                        *ended)

    def _on_session(self, event: dict[str, Any]) -> list[str]:
        frames = event.get("mailbox_frames", 0)
        self._counters["session_resumes"] += bool(event.get("resumed"))
        self._counters["session_mailbox_frames"] += frames if isinstance(frames, int) else 0
        if event.get("resumed"):
            logger.info("resumed session %s: %s frames kept while away", event.get("name"),
                        frames)
        wanted = {spec.remote_topic for spec in self.config.subscribe}
        patterns = event.get("subscriptions")
        return [p for p in patterns if isinstance(p, str) and p not in wanted] if isinstance(
            patterns, list) else []


def _unacked_segments(sock: Any) -> int | None:
    info = read_tcp_info(sock)
    return None if info is None else info.unacked


async def _discard(task: asyncio.Task[Dialed]) -> None:
    """Cancel an early dial; close its socket if it connected and was not used."""
    if not task.done():
        task.cancel()
    with contextlib.suppress(asyncio.CancelledError, Exception):
        dialed = await task
        dialed.sock.close()


def _close_exc(ws: LinkConnection) -> ConnectionClosed | None:
    """The close code and reason of a closed connection (None if not closed yet)."""
    try:
        return ws.protocol.close_exc
    except AssertionError:  # websockets asserts the connection is CLOSED
        return None
