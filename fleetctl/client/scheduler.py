"""The robot client's send scheduler: Robofleet Algorithms 1 and 2 plus fragments.

Pure state machine: no I/O, no asyncio, every method takes ``now_s`` from an injected
clock. The transport feeds it messages (:meth:`Scheduler.offer`), pulls frames to send
(:meth:`Scheduler.next_frame`), marks ack points (a WebSocket ping,
:meth:`Scheduler.ack_point`) and reports their pongs (:meth:`Scheduler.on_ack`).

- Algorithm 1 (Robofleet III-B): per-topic rate limit r (:class:`RateLimiter`); no_drop
  topics go to the FIFO Q_n, bounded in messages and bytes (tail drop, counted);
  droppable topics keep only their latest message in Q_f (replacement counted).
- Algorithm 2: Q_n first, then Q_f in DESCENDING ``priority x time since the topic's last
  send`` (Robofleet's code sorts ascending; that is a bug we do not copy). Ties go to the
  topic that waited longer, so priority 0 topics still progress when nothing else waits.
- Fragments (Pound section 5.1): frames longer than twice the link-time budget (adapted to
  the link rate, at most ``max_fragment_bytes``, see :meth:`Scheduler.whole_frame_bytes`) are
  split into fragments of :meth:`Scheduler.fragment_bytes` and the choice above is made per
  fragment, so an urgent small message waits behind at most one fragment of a large one.
  A topic's "last send" is its last fragment, which makes fragment streams of equal score
  interleave instead of one topic hogging the link.
- Supersede: newer data for a droppable topic drops the remaining fragments of an older
  message still being sent, when what is left of the older one is more than the newer
  one: sending the newer whole then brings fresh data sooner than finishing the older
  would bring any. Otherwise the older one completes (the newer waits as the topic's
  latest): superseding a message of the same size throws away the link time already
  spent on it, and on a link slower than the topic every other message was abandoned,
  mostly sent (a 150 KB cloud at 5 Hz delivered 3 of 5 a second on a link that carried
  5). To rule out livelock, at most ``max_consecutive_supersedes`` messages of a topic
  are superseded in a row; the next one runs to completion.
- Keyframes (video, :mod:`fleetctl.client.ros.videotopic`): a message offered with
  ``keyframe=True`` is what later frames of its topic depend on. A keyframe replaces any
  queued message of its topic and supersedes one being sent by the rule above, but a
  delta frame never replaces a queued
  keyframe nor supersedes one being sent: the delta is dropped instead (counted in
  ``dropped_behind_keyframe``; the video hook sees the drop and makes its next frame a
  keyframe).
- In flight = sent and not yet acknowledged by a pong to a later ping. The window is
  delay-based: it grows while the queueing delay (RTT - min RTT) is under
  ``target_queue_delay_s`` and shrinks above it, floored at one fragment (a message sent
  whole may fill the pipe up to the whole-frame limit, :meth:`Scheduler.whole_frame_bytes`,
  when that is larger: it should not wait a round trip behind a small frame), so a clean
  link is not capped at one message per RTT and a congested one does not build a queue
  (why not BBR's rate x min RTT: see :meth:`Scheduler._adapt_window`). It is also capped
  at the link rate x (min RTT + target): a token bucket's burst after idle makes acks
  look instant, and without the cap the window grew by the bucket's size into a queue
  that the delay signal only saw one (long) RTT later (see :meth:`Scheduler.rate_cap_bytes`).
  ``SchedulerConfig.fixed_window_messages`` gives Robofleet's fixed n_T instead.
- Disconnect: no_drop messages sent but not acknowledged, or partly sent, go back to the
  head of Q_n in their order (at-least-once; receivers dedupe by (topic, seq)); partly
  sent droppable messages are dropped (counted): the topic resumes with fresh data.
- Stale after an outage (issue 19): when a new connection opens after an outage, every
  held latest-only message published before the connection proved the path alive is
  dropped (:meth:`Scheduler.drop_stale`, counted in ``dropped_stale``), a fresh one is due
  within a period; so is one published before then that reaches the offer only later
  (``fresh_since_s`` of :meth:`Scheduler.offer`). On other reconnects (a server
  restart) only those older than ``stale_periods`` x their topic's measured publish
  period are. A dropped video frame
  (a topic that offers keyframes) leaves later delta frames without their reference, so
  the topic's deltas are dropped until its next keyframe (``dropped_behind_keyframe``;
  the video hook makes one after a drop or a new connection). Never dropped this way:
  no_drop messages and topics without a measured period (one offer so far: a latched
  map, nothing newer is coming); video keyframes only after an outage (measured: a
  keyframe held for 2.4 s arrived after the restore when they were exempt).
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from fleetctl.client.estimators import BusyRate, RateLimiter, WindowedExtremum

__all__ = [
    "BusyRate", "RateLimiter", "Scheduler", "SchedulerConfig", "SplitFn", "TopicFeedback",
    "TopicStats", "WindowedExtremum",
]


class SplitFn(Protocol):
    """Signature of :func:`fleetctl.wire.fragments.split`."""

    def __call__(
        self, frame: bytes, *, topic: str, message_id: int, max_fragment_bytes: int,
        no_drop: bool, payload_bytes: int | None = None,
    ) -> list[bytes]: ...


def _wire_split(
    frame: bytes, *, topic: str, message_id: int, max_fragment_bytes: int, no_drop: bool,
    payload_bytes: int | None = None,
) -> list[bytes]:
    from fleetctl.wire.fragmenter import fast_split

    fragments: list[bytes] = fast_split(frame, topic=topic, message_id=message_id,
                                        max_fragment_bytes=max_fragment_bytes, no_drop=no_drop,
                                        payload_bytes=payload_bytes)
    return fragments


@dataclass(frozen=True)
class SchedulerConfig:
    """Tunables of the scheduler.

    Attributes:
        max_fragment_bytes: Largest frame or fragment (bytes). Frames up to
            ``whole_frame_budgets`` x ``fragment_time_s`` of link time at the measured
            link rate (and at most this) go whole; longer ones are split into fragments
            of one budget rounded down to a power of two, between ``min_fragment_bytes``
            and this.
        min_fragment_bytes: Smallest fragment size on a slow link (bytes).
        initial_fragment_bytes: Fragment size before the first rate sample (bytes).
        fragment_time_s: Link time one fragment may take (seconds): the longest an urgent
            message waits behind a fragment of a large one.
        whole_frame_budgets: A frame up to this many fragment budgets (``fragment_time_s``
            of link time) goes whole; longer ones are split into fragments of one budget.
            Why 2: splitting a frame under two budgets long shortens the longest urgent
            wait behind it by less than half, and each split costs the frame one more
            message through every hop (robot, relay, each receiver) and, when the window
            binds, a round trip. Measured on the e2e ``peer-fanout`` link (12 Mbit/s over
            WireGuard): the 6 KB scan split into 4 + 2 KiB arrived 1.4-4 ms later at p50
            than whole (docs/client.md).
        fragments: False sends whole frames (the Robofleet baseline).
        no_drop_queue_messages: Bound of Q_n plus unacknowledged no_drop messages.
        no_drop_queue_bytes: Byte bound of the same.
        fixed_window_messages: Robofleet's n_T (frames in flight); None = adaptive window.
        initial_window_bytes: Window before the first RTT and rate samples (bytes).
        max_window_bytes: Upper bound of the adaptive window (bytes).
        max_window_messages: Upper bound of frames in flight (adaptive mode).
        window_gain: BBR cwnd gain of the ``bdp_bytes`` estimate (reported in stats).
        rate_cap_gain: The window is at most this x link rate x (min RTT +
            ``target_queue_delay_s``); None disables the cap.
        target_queue_delay_s: Queueing delay (RTT above the min RTT, seconds) the
            delay-based window steers to: larger moves more on a fast link, smaller keeps
            urgent messages quicker on a slow one.
        min_rtt_filter_s: Window of the min-RTT filter (seconds).
        rate_filter_s: Window of the max-delivery-rate filter (seconds, stats only).
        link_rate_window_s: Window of the link rate used to size fragments: bytes acked
            over busy time (seconds).
        link_rate_hold_s: Fragments are sized by the highest such rate in this window
            (seconds), so they shrink only after the link stayed slower this long.
        ack_every_window_fraction: An ack point is due after this fraction of the window
            was sent without one, so acks return while the window is still open.
        max_consecutive_supersedes: Supersedes in a row per droppable topic before the
            in-progress message is protected (livelock guard).
        rate_tolerance: Fraction of the period a message may come early and still pass
            the rate limit (ROS timers jitter).
        first_message_id: First fragment message id; pass a time-based value so ids of
            a restarted client are newer than the previous run's.
        stale_periods: On a reconnect that did not follow an outage, a held latest-only
            message older than this many publish periods of its topic is dropped
            (:meth:`drop_stale`): its topic stopped or slowed, it is not the latest.
        period_gain: Gain of the moving average of a topic's offer intervals.
    """

    max_fragment_bytes: int = 4194304
    min_fragment_bytes: int = 1024
    initial_fragment_bytes: int = 4096
    fragment_time_s: float = 0.003
    whole_frame_budgets: float = 2.0
    fragments: bool = True
    no_drop_queue_messages: int = 10000
    no_drop_queue_bytes: int = 64 * 1024 * 1024
    fixed_window_messages: int | None = None
    initial_window_bytes: int = 16 * 1024
    max_window_bytes: int = 16 * 1024 * 1024
    max_window_messages: int = 4096
    window_gain: float = 2.0
    rate_cap_gain: float | None = 1.0
    target_queue_delay_s: float = 0.004
    min_rtt_filter_s: float = 10.0
    rate_filter_s: float = 2.0
    link_rate_window_s: float = 0.5
    link_rate_hold_s: float = 4.0
    ack_every_window_fraction: float = 0.25
    max_consecutive_supersedes: int = 1
    rate_tolerance: float = 0.05
    first_message_id: int = 0
    stale_periods: float = 1.5
    period_gain: float = 0.125


@dataclass
class TopicStats:
    """Counters of one remote topic (messages unless the name says bytes/frames)."""

    offered: int = 0
    rate_limited: int = 0
    sent: int = 0
    sent_frames: int = 0
    sent_bytes: int = 0
    acked: int = 0
    dropped_replaced: int = 0
    dropped_superseded: int = 0
    dropped_overflow: int = 0
    dropped_disconnect: int = 0
    dropped_invalid: int = 0
    dropped_behind_keyframe: int = 0
    dropped_stale: int = 0
    requeued: int = 0

    @property
    def dropped(self) -> int:
        """Every message of the topic the scheduler dropped, whatever the reason."""
        return (self.dropped_replaced + self.dropped_superseded + self.dropped_overflow
                + self.dropped_disconnect + self.dropped_invalid
                + self.dropped_behind_keyframe + self.dropped_stale)


@dataclass(frozen=True)
class TopicFeedback:
    """What a producer adapting to the link needs about one topic (video bitrate and
    keyframes). Counters are cumulative.

    Attributes:
        link_rate_Bps: The link rate the fragments are sized by (bytes/s; 0 before the
            first estimate; see :meth:`Scheduler.rate_cap_bytes`).
        dropped: Messages of the topic dropped so far (:attr:`TopicStats.dropped`).
        sent_bytes: Bytes of the topic sent so far.
        busy: A message of the topic waits, or is partly sent.
        higher_priority_sent_bytes: Bytes sent so far by topics of a higher priority.
        wire_share: Bytes on the wire per byte sent, lately (the rate and the counts are
            in frame bytes, before the uplink deflate: 1.0 here, the link fills it in,
            :mod:`fleetctl.client.slowdeflate`).
    """

    link_rate_Bps: float
    dropped: int
    sent_bytes: int
    busy: bool
    higher_priority_sent_bytes: int
    wire_share: float = 1.0


class _Message:
    __slots__ = ("fragments", "frame", "keyframe", "message_id", "next_index", "no_drop",
                 "offered_s", "published_s", "topic")

    def __init__(self, topic: _Topic, frame: bytes, no_drop: bool,
                 keyframe: bool = False, offered_s: float = 0.0,
                 published_s: float | None = None) -> None:
        self.topic = topic
        self.offered_s = offered_s
        # When it was published (the scheduler's clock), as far as the offer knew it:
        # what decides whether it is stale after an outage (drop_stale).
        self.published_s = offered_s if published_s is None else published_s
        self.frame = frame
        self.no_drop = no_drop
        self.keyframe = keyframe
        self.fragments: list[bytes] | None = None
        self.message_id = 0
        self.next_index = 0

    @property
    def started(self) -> bool:
        return self.fragments is not None and self.next_index > 0


def _unsent_bytes(msg: _Message) -> float:
    """What is left to send of a message being sent, in bytes of its frame: the share of
    its fragments' bytes not sent yet (headers and all, so that a message of the same size
    never has more left than a new one, however its fragments were cut)."""
    assert msg.fragments is not None
    total = sum(len(fragment) for fragment in msg.fragments)
    unsent = sum(len(fragment) for fragment in msg.fragments[msg.next_index:])
    return len(msg.frame) * unsent / total


@dataclass(eq=False)
class _Topic:
    name: str
    priority: float
    last_sent_s: float
    pending: _Message | None = None  # droppable: latest not yet started
    current: _Message | None = None  # droppable: partly sent
    supersede_streak: int = 0
    last_offer_s: float | None = None
    last_published_s: float | None = None  # the last offer's publish time, as offer knew it
    period_s: float | None = None  # moving average of offer intervals
    video: bool = False  # a keyframe was offered: later frames depend on earlier ones
    awaiting_keyframe: bool = False  # a frame was dropped as stale: deltas are useless
    stats: TopicStats = field(default_factory=TopicStats)


@dataclass
class _AckPoint:
    token: int
    sent_s: float
    sent_bytes_total: int
    sent_frames_total: int
    delivered_bytes: int
    delivered_s: float
    app_limited: bool


class Scheduler:
    """Decides which frame goes next on the link. See the module docstring.

    Args:
        config: Tunables.
        split: Fragmenter; by default :func:`fleetctl.wire.fragmenter.fast_split`
            (byte-identical to :func:`fleetctl.wire.fragments.split`, cheaper).
    """

    def __init__(self, config: SchedulerConfig | None = None, *, split: SplitFn | None = None):
        self.config = config or SchedulerConfig()
        self._split: SplitFn = split or _wire_split
        self.rate_limiter = RateLimiter(self.config.rate_tolerance)
        self._topics: dict[str, _Topic] = {}
        self._qn: deque[_Message] = deque()
        self._qn_bytes = 0
        self._message_ids = itertools.count(self.config.first_message_id)
        # Completed messages not yet acknowledged: (sent_bytes_total at their end, message).
        self._unacked: deque[tuple[int, _Message]] = deque()
        self._unacked_no_drop = 0
        self._unacked_no_drop_bytes = 0
        self._sent_bytes_total = 0
        self._sent_frames_total = 0
        self._acked_bytes_total = 0
        self._acked_frames_total = 0
        self._delivered_s = 0.0
        self._ack_points: deque[_AckPoint] = deque()
        self._tokens = itertools.count(1)
        self._min_rtt = WindowedExtremum(self.config.min_rtt_filter_s, keep_max=False)
        self._max_rate = WindowedExtremum(self.config.rate_filter_s, keep_max=True)
        self._busy_rate = BusyRate(self.config.link_rate_window_s)
        # A connection's first rate sample (at, bytes, busy s), held until the next one
        # confirms it (_add_rate_sample).
        self._held_rate_sample: tuple[float, int, float] | None = None
        self._rate_confirmed = False
        # Held at its max: if a CPU-bound receiver slows the acks, shrinking fragments
        # (more frames, more per-frame work) would slow it further, down to the minimum.
        self._link_rate = WindowedExtremum(self.config.link_rate_hold_s, keep_max=True)
        self._last_rtt_s: float | None = None
        self.no_drop_overflow = 0
        self.last_error: str | None = None
        self._delay_window = float(self.config.initial_window_bytes)
        self._fragment = self._whole = self._window = 0
        self._link_rate_Bps = 0.0
        # Set by the link while it deflates every message: a topic's fragments' share of
        # its message, so that deflated each fills whole TCP segments
        # (fleetctl.client.segmentfill); None, or None for the topic: fragment_bytes().
        self.fragment_sizer: Callable[[str], int | None] | None = None
        self._update_limits()

    # -- Algorithm 1 ------------------------------------------------------------------

    def register_topic(self, topic: str, priority: float, now_s: float) -> None:
        """Declare a topic up front (its last-send time starts at *now_s*).

        Topics can also appear first in :meth:`offer`; registering them lets
        :meth:`admit` run on another thread without growing the topic table.
        """
        self._topic(topic, priority, now_s).priority = priority

    def admit(self, topic: str, rate_limit_hz: float | None, now_s: float) -> bool:
        """Rate-limit check before the caller encodes a message (Algorithm 1, 4-6).

        Args:
            topic: Remote topic.
            rate_limit_hz: The topic's limit in Hz, None for no limit.
            now_s: Clock in seconds.

        Returns:
            False when the message must be skipped (counted as rate_limited).
        """
        if self.rate_limiter.admit(topic, rate_limit_hz, now_s):
            return True
        self._topic(topic, 1.0, now_s).stats.rate_limited += 1
        return False

    def offer(self, topic: str, frame: bytes, now_s: float, *, priority: float,
              no_drop: bool, keyframe: bool = False, published_s: float | None = None,
              fresh_since_s: float | None = None) -> bool:
        """Queue an encoded frame (Algorithm 1, 7-15).

        Args:
            topic: Remote topic of the frame.
            frame: One complete wire frame (its own metadata inside).
            now_s: Clock in seconds.
            priority: Non-negative Algorithm 2 weight (updates the topic's weight).
            no_drop: True queues in the bounded FIFO Q_n; False keeps latest only.
            keyframe: A droppable video keyframe: later frames of the topic depend on it,
                so they never replace it (see the module docstring).
            published_s: When the message was published, on this clock (None: *now_s*).
            fresh_since_s: A latest-only message published before this is stale (it was
                published into the last outage and reached the offer only after the
                path came back): it is dropped at once, counted in ``dropped_stale``,
                unless its topic has no measured period (as in :meth:`drop_stale`).
                None: no such check.

        Returns:
            False when a no_drop message was refused because Q_n is full (counted in
            ``no_drop_overflow`` and the topic's ``dropped_overflow``).
        """
        t = self._topic(topic, priority, now_s)
        t.priority = priority
        t.stats.offered += 1
        self._measure_period(t, now_s)
        msg = _Message(t, frame, no_drop, keyframe, now_s, published_s)
        t.last_published_s = msg.published_s
        if no_drop:
            return self._push_no_drop(msg)
        if (fresh_since_s is not None and msg.published_s < fresh_since_s
                and t.period_s is not None):  # as drop_stale: a latched map's one offer stays
            t.stats.dropped_stale += 1
            return True
        self._update_droppable(t, msg)
        return True

    def _topic(self, name: str, priority: float, now_s: float) -> _Topic:
        t = self._topics.get(name)
        if t is None:
            t = self._topics[name] = _Topic(name, priority, last_sent_s=now_s)
        return t

    def next_publish_after(self, t_s: float) -> float:
        """When the soonest message after *t_s* is expected to be published: each topic
        with a measured period publishes again at its last publish time plus whole
        periods (``inf``: no topic has one yet). Used while the link is down to dial just
        before it (the dialer's *ahead*). Why the publish time and not the offer: a
        message is kept after an outage when it was published after the winning SYN's
        answer came (``drop_stale``), and it reaches the offer 0.5-3 ms after its publish
        (DDS, the take, the encode); a SYN aimed at the offer left too late for a scan in
        traced e2e runs (0.4 ms before its publish, answered after it)."""
        soonest = math.inf
        for t in self._topics.values():
            last, period = t.last_published_s, t.period_s
            if last is None or period is None or period <= 0.0:
                continue
            nxt = last + max(1, math.floor((t_s - last) / period) + 1) * period
            if nxt <= t_s:  # the division rounded down a whole period
                nxt += period
            soonest = min(soonest, nxt)
        return soonest

    def _measure_period(self, t: _Topic, now_s: float) -> None:
        """Moving average of the topic's offer intervals (an srtt-like filter)."""
        if t.last_offer_s is not None:
            dt = max(0.0, now_s - t.last_offer_s)
            gain = self.config.period_gain
            t.period_s = dt if t.period_s is None else t.period_s + gain * (dt - t.period_s)
        t.last_offer_s = now_s

    def drop_stale(self, now_s: float, *, after_outage: bool,
                   alive_since_s: float | None = None) -> int:
        """Drop held latest-only messages that would arrive stale on a new connection.

        Call when a connection opens. *after_outage*: the previous connection's path went
        silent, so every held message published before *alive_since_s* (from when the
        new connection proves the path worked; None: not known) may have been published
        while it was dead: its latency would
        be its age plus the backlog it waits behind (no_drop messages of the outage),
        while the topic's next message is due within a period and would wait behind it.
        A message published after it is a few milliseconds old (the handshake) and is
        kept: dropping it made a 10 Hz scan published during the handshake wait a whole
        period for the next one (e2e ``peer``: 0.11-0.13 s in 4 of 10 cuts).
        Measured in the e2e dropout: keeping held messages younger than half a period
        (a 75 KB image among them) kept the pose latency over 2x its median for 0.29 s
        after the restore, dropping them all brought it back in 0.03 s. Otherwise only
        messages older than ``stale_periods`` periods (and never keyframes) are dropped.
        Topics without a measured period keep theirs; a video topic that lost a frame
        drops its deltas until its next keyframe (see the module docstring).

        Returns:
            How many were dropped (each counted in its topic's ``dropped_stale``).
        """
        dropped = 0
        limit = self.config.stale_periods
        for t in self._topics.values():
            msg = t.pending
            if msg is None or t.period_s is None or (msg.keyframe and not after_outage):
                continue
            if after_outage and alive_since_s is not None and msg.published_s >= alive_since_s:
                continue  # published while the path worked again: fresh
            if after_outage or now_s - msg.offered_s > limit * t.period_s:
                t.pending = None
                t.awaiting_keyframe = t.video
                t.stats.dropped_stale += 1
                dropped += 1
        return dropped

    def _push_no_drop(self, msg: _Message) -> bool:
        count = len(self._qn) + self._unacked_no_drop
        size = self._qn_bytes + self._unacked_no_drop_bytes + len(msg.frame)
        if count >= self.config.no_drop_queue_messages or size > self.config.no_drop_queue_bytes:
            self.no_drop_overflow += 1
            msg.topic.stats.dropped_overflow += 1
            return False
        self._qn.append(msg)
        self._qn_bytes += len(msg.frame)
        return True

    def _update_droppable(self, t: _Topic, msg: _Message) -> None:
        if msg.keyframe:
            t.video, t.awaiting_keyframe = True, False
        elif t.awaiting_keyframe:
            t.stats.dropped_behind_keyframe += 1  # its reference was dropped as stale
            return
        if not msg.keyframe and t.pending is not None and t.pending.keyframe:
            t.stats.dropped_behind_keyframe += 1  # the keyframe it would replace stays
            return
        if (t.current is not None and t.supersede_streak < self.config.max_consecutive_supersedes
                and (msg.keyframe or not t.current.keyframe)
                and _unsent_bytes(t.current) > len(msg.frame)):
            t.current = None
            t.supersede_streak += 1
            t.stats.dropped_superseded += 1
        if t.pending is not None:
            t.stats.dropped_replaced += 1
        t.pending = msg

    # -- Algorithm 2 ------------------------------------------------------------------

    def next_frame(self, now_s: float) -> bytes | None:
        """The next frame to send now, or None (nothing queued or window full).

        The returned frame counts as in flight until an ack point after it is acked. A
        message the splitter rejects (e.g. no readable metadata) is dropped, counted in
        ``dropped_invalid`` and remembered in ``last_error``.
        """
        topic, msg, frame = self._candidate(now_s)
        if msg is None or not self._window_allows(len(frame), msg):
            return None
        if topic is not None and topic.current is None:
            topic.current, topic.pending = msg, None
        msg.next_index += 1
        self._account_sent(msg, frame, now_s)
        return frame

    def _candidate(self, now_s: float) -> tuple[_Topic | None, _Message | None, bytes]:
        """The message Algorithm 2 picks and its next fragment (dropping invalid ones)."""
        while True:
            topic, msg = self._choose(now_s)
            if msg is None:
                return None, None, b""
            try:
                return topic, msg, self._peek_fragment(msg)
            except Exception as exc:  # the splitter's WireError; never kill the link
                self._drop_invalid(topic, msg, exc)

    def _drop_invalid(self, topic: _Topic | None, msg: _Message, exc: Exception) -> None:
        msg.topic.stats.dropped_invalid += 1
        self.last_error = f"dropped a message on {msg.topic.name}: {exc}"
        if topic is None:
            self._qn.popleft()
            self._qn_bytes -= len(msg.frame)
        elif topic.current is msg:
            topic.current = None
        else:
            topic.pending = None

    def _choose(self, now_s: float) -> tuple[_Topic | None, _Message | None]:
        if self._qn:
            return None, self._qn[0]
        best: _Topic | None = None
        best_key = (-1.0, -math.inf)
        for t in self._topics.values():
            if t.current is None and t.pending is None:
                continue
            wait = now_s - t.last_sent_s
            key = (t.priority * wait, wait)  # descending f; longer wait breaks ties
            if key > best_key:
                best, best_key = t, key
        if best is None:
            return None, None
        return best, best.current or best.pending

    def _peek_fragment(self, msg: _Message) -> bytes:
        if msg.fragments is None:
            msg.message_id = next(self._message_ids)
            cfg = self.config
            if cfg.fragments and len(msg.frame) > self._whole:
                share = (None if self.fragment_sizer is None
                         else self.fragment_sizer(msg.topic.name))
                # Passed only when set: a splitter given to the scheduler need not know it.
                msg.fragments = self._split(
                    msg.frame, topic=msg.topic.name, message_id=msg.message_id,
                    max_fragment_bytes=self.fragment_bytes(), no_drop=msg.no_drop,
                    **({} if share is None else {"payload_bytes": share}))
            else:
                msg.fragments = [msg.frame]
        return msg.fragments[msg.next_index]

    def _window_allows(self, size: int, msg: _Message) -> bool:
        in_frames = self._sent_frames_total - self._acked_frames_total
        if self.config.fixed_window_messages is not None:
            return in_frames < self.config.fixed_window_messages
        if in_frames >= self.config.max_window_messages:
            return False
        in_bytes = self.in_flight_bytes
        # An empty pipe always takes one frame, even one larger than the window.
        if in_bytes == 0 or in_bytes + size <= self._window:
            return True
        # A message that goes whole may use the window up to the whole-frame limit: the
        # budget decided it is short enough not to be split, so it should not wait a round
        # trip behind a small frame in flight either (a 6.4 KB scan behind a 256 B pose
        # with the rate cap at 5.4 KB: the e2e peer-fanout scan's p50 at 16 consumers went
        # from 8.2-10.4 to 4.6-6.0 ms, docs/client.md). Fragments keep the window: they are what an
        # urgent message may wait behind.
        return (self.config.fragments and msg.fragments is not None
                and len(msg.fragments) == 1 and in_bytes + size <= self._whole)

    def _account_sent(self, msg: _Message, frame: bytes, now_s: float) -> None:
        if self.in_flight_bytes == 0:
            self._delivered_s = now_s  # restart from idle (BBR): rate counts from here
        self._sent_bytes_total += len(frame)
        self._sent_frames_total += 1
        t = msg.topic
        t.last_sent_s = now_s
        t.stats.sent_frames += 1
        t.stats.sent_bytes += len(frame)
        assert msg.fragments is not None
        if msg.next_index < len(msg.fragments):
            return
        t.stats.sent += 1
        if msg.no_drop:
            self._qn.popleft()
            self._qn_bytes -= len(msg.frame)
            self._unacked_no_drop += 1
            self._unacked_no_drop_bytes += len(msg.frame)
        else:
            t.current = None
            t.supersede_streak = 0
        self._unacked.append((self._sent_bytes_total, msg))

    # -- acknowledgements and the window ------------------------------------------------

    @property
    def in_flight_bytes(self) -> int:
        """Bytes sent and not yet acknowledged."""
        return self._sent_bytes_total - self._acked_bytes_total

    @property
    def no_drop_queued(self) -> int:
        """no_drop messages waiting in Q_n (not yet completely sent)."""
        return len(self._qn)

    @property
    def no_drop_held(self) -> tuple[int, int]:
        """(messages, bytes) of no_drop held against the FIFO's bounds: queued in Q_n plus
        sent and not yet acknowledged (what ``no_drop_queue_messages`` and
        ``no_drop_queue_bytes`` limit)."""
        return (len(self._qn) + self._unacked_no_drop,
                self._qn_bytes + self._unacked_no_drop_bytes)

    @property
    def in_flight_frames(self) -> int:
        """Frames sent and not yet acknowledged."""
        return self._sent_frames_total - self._acked_frames_total

    def wants_ack_point(self, now_s: float) -> bool:
        """True when the transport should send a ping now.

        Due when frames were sent since the last ack point and either a fraction of the
        window went out without one (:meth:`ack_due`), or nothing more can be sent right
        now (queue empty or window full: only a pong can open it).
        """
        return self.has_unpinged() and (self.ack_due() or not self._can_send(now_s))

    def has_unpinged(self) -> bool:
        """True when frames were sent after the last ack point."""
        points = self._ack_points
        last = points[-1].sent_frames_total if points else self._acked_frames_total
        return self._sent_frames_total != last

    def ack_due(self) -> bool:
        """True when ``ack_every_window_fraction`` of the window went out without a ping.

        Cheap enough for every frame; a sender that stops because :meth:`next_frame`
        returned None should ping when :meth:`has_unpinged` (that is the other case of
        :meth:`wants_ack_point`).
        """
        points = self._ack_points
        cfg = self.config
        if cfg.fixed_window_messages is not None:
            last_frames = points[-1].sent_frames_total if points else self._acked_frames_total
            return self._sent_frames_total - last_frames >= max(
                1.0, cfg.ack_every_window_fraction * cfg.fixed_window_messages)
        last_bytes = points[-1].sent_bytes_total if points else self._acked_bytes_total
        return self._sent_bytes_total - last_bytes >= (
            cfg.ack_every_window_fraction * self._window)

    def _can_send(self, now_s: float) -> bool:
        _, msg, frame = self._candidate(now_s)
        return msg is not None and self._window_allows(len(frame), msg)

    def has_sendable(self) -> bool:
        """True when a frame is queued (whether or not the window allows it)."""
        return bool(self._qn) or any(
            t.current is not None or t.pending is not None for t in self._topics.values())

    def ack_point(self, now_s: float) -> int:
        """Record a ping sent now; returns its token (pass it to :meth:`on_ack`)."""
        point = _AckPoint(
            token=next(self._tokens), sent_s=now_s, sent_bytes_total=self._sent_bytes_total,
            sent_frames_total=self._sent_frames_total, delivered_bytes=self._acked_bytes_total,
            delivered_s=self._delivered_s, app_limited=not self.has_sendable())
        self._ack_points.append(point)
        return point.token

    def on_ack(self, token: int, now_s: float) -> bool:
        """A pong for *token* arrived: everything sent before that ping is delivered.

        Returns:
            False for an unknown token (e.g. from before a disconnect); ignored.
        """
        if not any(p.token == token for p in self._ack_points):
            return False
        while self._ack_points:
            point = self._ack_points.popleft()
            if point.token == token:
                break
        self._acknowledge(point, now_s)
        return True

    def _acknowledge(self, point: _AckPoint, now_s: float) -> None:
        acked_now = max(0, point.sent_bytes_total - self._acked_bytes_total)
        self._acked_bytes_total = max(self._acked_bytes_total, point.sent_bytes_total)
        self._acked_frames_total = max(self._acked_frames_total, point.sent_frames_total)
        while self._unacked and self._unacked[0][0] <= self._acked_bytes_total:
            _, msg = self._unacked.popleft()
            msg.topic.stats.acked += 1
            if msg.no_drop:
                self._unacked_no_drop -= 1
                self._unacked_no_drop_bytes -= len(msg.frame)
        rtt = now_s - point.sent_s
        self._last_rtt_s = rtt
        self._min_rtt.add(now_s, rtt)
        self._adapt_window(rtt, acked_now, point.app_limited)
        busy_s = now_s - self._delivered_s  # since the last ack or the restart from idle
        # Acks that arrive together (one read of several pongs) still count their bytes:
        # dropping the zero-time ones underestimated the rate, and so the window cap.
        # An app-limited ack (nothing was waiting when its ping went) of less than an
        # initial fragment measured the round trip of a small message, not the link: a
        # lone 256 B pose acked after 2.5 ms reads 0.1 MB/s. Counted, such acks put the
        # e2e peer load (a pose at 20 Hz, a 6 KB scan at 10 Hz, 4 Mbit/s over
        # WireGuard) at 0.54 MB/s on 6 of 16 connections of one run: the scan went as
        # 1 KiB fragments under a 2.8 KB window, whose round trips kept the rate there,
        # at 8-15 ms p50 for the whole connection instead of 3.5-4.4 ms. A larger one
        # (a whole scan) does say what the link moves: on a 1 Mbit/s link its round trip
        # is mostly the link's time, and it must still shrink the fragments there.
        if acked_now > 0 and busy_s >= 0 and (
                not point.app_limited or acked_now >= self.config.initial_fragment_bytes):
            self._add_rate_sample(now_s, acked_now, busy_s)
            # Less than an initial fragment acknowledged is a small message's round trip,
            # not the link's rate: a new connection's first pose measured 0.2 MB/s on a
            # 12 Mbit/s link, and its scans went in 1 KiB fragments for ~0.6 s. Until
            # then the initial sizes hold, as before the first ack.
            if self._busy_rate.bytes >= self.config.initial_fragment_bytes:
                self._link_rate.add(now_s, self._busy_rate.rate())
        elapsed = now_s - point.delivered_s
        if elapsed > 0:
            rate = (self._acked_bytes_total - point.delivered_bytes) / elapsed
            # App-limited samples underestimate the link; keep them only if they raise it.
            if not point.app_limited or rate > self._max_rate.value(now_s, 0.0):
                self._max_rate.add(now_s, rate)
        self._update_limits()
        self._delivered_s = now_s

    def _add_rate_sample(self, now_s: float, acked: int, busy_s: float) -> None:
        """Count *acked* bytes over *busy_s* in the link rate, except a connection's first
        sample, which waits for the next one to confirm it.

        A new connection's first large message runs a cold path on every hop: the e2e
        peer load's first scan after a reconnect took 13.8 ms where the next took ~4
        (docs/recovery.md, "A cold first acknowledgement"). Counted at once, it read the
        4 Mbit/s link (whose 16 KB bucket that load crosses at 20-24 Mbit/s) as 3.7
        Mbit/s, and the scans after it went as 1 KiB fragments, whose own round trips
        kept the rate there until the 0.5 s window forgot the cold one (scans at 21.9,
        17.0, 8.4 ms). So the first sample is held, the initial sizes meanwhile, until
        the next sample with busy time of its own: if that reads the link faster, the
        first was cold and is dropped; if not, both count (a slow link: its rate is set
        one message later). Acks read together share one arrival time, so the ones after
        the first have no busy time of their own: they join the held sample (one
        measurement), or their bytes would count over no time.
        """
        if self._rate_confirmed:
            self._busy_rate.add(now_s, acked, busy_s)
            return
        held = self._held_rate_sample
        if held is None or busy_s <= 0:
            held_at, held_bytes, held_busy = held or (now_s, 0, 0.0)
            self._held_rate_sample = (held_at, held_bytes + acked, held_busy + busy_s)
            return
        self._rate_confirmed, self._held_rate_sample = True, None
        held_at, held_bytes, held_busy = held
        # held rate <= this rate, without dividing by a held busy time of zero
        if held_bytes * busy_s > acked * held_busy:
            self._busy_rate.add(held_at, held_bytes, held_busy)
        self._busy_rate.add(now_s, acked, busy_s)

    def rescale_rates(self, factor: float) -> None:
        """The bytes the link's rates were measured in now count *factor* times (0 <
        factor <= 1): the robot stopped deflating fragments
        (:mod:`fleetctl.client.slowdeflate`), so a byte it sends takes 1 / factor times
        the link time it took. Without this the fragments and the window would keep the
        compressed sizes for the rate hold (4 s), raw: an urgent message behind a raw
        64 KB fragment on a 6 Mbit/s link."""
        if not 0 < factor < 1:
            return
        self._busy_rate.scale(factor)
        if self._held_rate_sample is not None:
            at, held_bytes, busy = self._held_rate_sample
            self._held_rate_sample = (at, int(held_bytes * factor), busy)
        self._link_rate.scale(factor)
        self._max_rate.scale(factor)
        self._update_limits()

    @property
    def sent_bytes_total(self) -> int:
        """Frame bytes taken for sending since this scheduler began (never reset)."""
        return self._sent_bytes_total

    @property
    def link_rate_Bps(self) -> float:
        """The link rate the fragments are sized by (frame bytes/s; 0 before samples)."""
        return self._link_rate_Bps

    def min_rtt_s(self, now_s: float | None = None) -> float | None:
        """Minimum RTT over the filter window in seconds, None before the first sample."""
        value = self._min_rtt.value(now_s, -1.0)
        return None if value < 0 else value

    def topic_feedback(self, topic: str) -> TopicFeedback:
        """Link rate and the counters of *topic* (all zero for a topic never offered).

        Reads plain attributes and copies the topic table in one step, so another thread
        may call it while the loop's thread runs the scheduler (CPython's GIL makes each
        read atomic); the figures may be one frame apart from each other.
        """
        t = self._topics.get(topic)
        priority = t.priority if t is not None else math.inf
        higher = sum(other.stats.sent_bytes for other in list(self._topics.values())
                     if other.priority > priority)
        if t is None:
            return TopicFeedback(self._link_rate_Bps, 0, 0, False, higher)
        return TopicFeedback(
            link_rate_Bps=self._link_rate_Bps, dropped=t.stats.dropped,
            sent_bytes=t.stats.sent_bytes,
            busy=t.pending is not None or t.current is not None,
            higher_priority_sent_bytes=higher)

    def delivery_rate_bps(self, now_s: float | None = None) -> float:
        """Maximum delivery rate over the filter window in bytes/s (0 before samples)."""
        return self._max_rate.value(now_s, 0.0)

    def window_bytes(self) -> int:
        """Current in-flight byte limit (adaptive mode): the delay-based window, floored
        at one fragment and capped at ``max_window_bytes``."""
        return self._window

    def _update_limits(self) -> None:
        """Recompute the cached fragment size and window (they change only on acks)."""
        cfg = self.config
        rate = self._link_rate.value(None, 0.0)
        self._link_rate_Bps = rate  # a plain float for topic_feedback() on other threads
        budget = self._compute_budget_bytes(rate)
        if rate <= 0:
            self._fragment = budget  # the configured initial size, as given
        else:
            # Rounding never goes below the configured floor (a cap under
            # min_fragment_bytes that is not a power of two is itself the size).
            self._fragment = max(min(cfg.min_fragment_bytes, cfg.max_fragment_bytes),
                                 _power_of_two_floor(budget))
        # Before the first rate sample too (a new connection): the first scan after an
        # outage went as 4 + 2 KiB and arrived 2-3x later than the scans after it.
        self._whole = min(cfg.max_fragment_bytes, int(budget * cfg.whole_frame_budgets))
        floor = float(self._fragment if cfg.fragments else 1)
        window = min(self._delay_window, self.rate_cap_bytes())
        self._window = int(min(max(window, floor), self.config.max_window_bytes))

    def rate_cap_bytes(self) -> float:
        """What the link delivers in a min RTT plus the target queue delay (bytes).

        The link rate is bytes acknowledged over busy time (:class:`BusyRate`, held at its
        maximum for ``link_rate_hold_s``), which a token bucket's burst does not inflate
        the way per-ack rate samples are inflated. On a fast link the cap does not bind:
        there the window-limited rate is window / RTT, so the cap is window x (min RTT +
        target) / RTT, above the window until the queueing delay exceeds the target, where
        the delay-based window shrinks anyway. Infinite before the first samples.
        """
        gain = self.config.rate_cap_gain
        rate = self._link_rate.value(None, 0.0)
        min_rtt = self.min_rtt_s()
        if gain is None or rate <= 0 or min_rtt is None:
            return float("inf")
        return gain * rate * (min_rtt + self.config.target_queue_delay_s)

    def bdp_bytes(self) -> float:
        """BBR's estimate ``window_gain x max delivery rate x min RTT`` (stats only)."""
        rtt = self.min_rtt_s()
        return self.config.window_gain * self.delivery_rate_bps() * rtt if rtt else 0.0

    def fragment_bytes(self) -> int:
        """The fragment size in use now (bytes); see ``SchedulerConfig.fragment_time_s``."""
        return self._fragment

    def whole_frame_bytes(self) -> int:
        """The longest frame sent unsplit now (bytes): ``whole_frame_budgets`` link-time
        budgets, not rounded, at most ``max_fragment_bytes`` (see
        :meth:`_compute_budget_bytes`)."""
        return self._whole

    def _compute_budget_bytes(self, rate: float) -> int:
        """The link-time budget of one fragment at *rate* (bytes/s, 0 before the first
        sample), between the fragment bounds.

        Pound sizes fragments to the radio's MTU; here the link is TCP, so the size
        follows the link rate instead: small enough that an urgent message waits at most
        ``fragment_time_s`` behind a fragment, large enough that a fast link is not
        limited by per-frame costs (a 16 KB fragment on a 1.5 GB/s loopback: 3x slower).
        A frame within ``whole_frame_budgets`` of it goes whole; a longer one is split
        into fragments of the power of two below it (:meth:`fragment_bytes`), which keeps
        the fragmenter's per-size templates reusable. Rounding only the split size
        matters for frames just over a power of two: a cloud of 1 MiB of points is a
        1 MiB + 700 B frame, which a rounded budget split into 1 MiB and 700 B, two
        frames and a reassembly per cloud, however fast the link.
        """
        cfg = self.config
        top = cfg.max_fragment_bytes
        if rate <= 0:
            return min(top, cfg.initial_fragment_bytes)
        low = min(cfg.min_fragment_bytes, top)
        return max(low, min(top, int(rate * cfg.fragment_time_s)))

    def _adapt_window(self, rtt_s: float, acked_bytes: int, app_limited: bool) -> None:
        """Delay-based window update (LEDBAT-like, with doubling growth).

        Queueing delay = this RTT - min RTT. Below ``target_queue_delay_s`` the window
        grows by up to the bytes just acknowledged (doubling per RTT on an empty queue);
        above it, it shrinks by up to as much (halving per RTT at twice the target). Why
        not BBR's ``gain x rate x min RTT``: on a Python event loop the ack turnaround
        under load exceeds the idle min RTT by more than BBR's gain of 2, and the
        estimate collapses to one fragment per RTT (measured: 6 MB/s where plain
        websockets moved 225 MB/s); and its 2 s max-rate filter keeps a stale large
        window after the link rate drops, which is the queue this window prevents.
        """
        cfg = self.config
        min_rtt = self.min_rtt_s()
        if min_rtt is None:
            return
        target = cfg.target_queue_delay_s
        off = max(-1.0, min(1.0, (target - (rtt_s - min_rtt)) / target))
        if off > 0 and app_limited:
            return  # the window was not in use: no evidence that more would fit
        window = self._delay_window + off * acked_bytes
        floor = float(self._fragment if cfg.fragments else 1)
        self._delay_window = min(max(window, floor), float(cfg.max_window_bytes))

    # -- connection life cycle ----------------------------------------------------------

    def on_disconnect(self, now_s: float) -> None:
        """The link died: requeue unacknowledged no_drop messages, drop partial droppables.

        No_drop messages sent but not acknowledged go back to the head of Q_n in their
        original order and are sent again in full (new fragment message id).
        """
        requeue = [msg for _, msg in self._unacked if msg.no_drop]
        self._unacked.clear()
        self._unacked_no_drop = self._unacked_no_drop_bytes = 0
        for msg in reversed(requeue):
            msg.topic.stats.requeued += 1
            self._qn.appendleft(msg)
            self._qn_bytes += len(msg.frame)
        for msg in self._qn:
            if msg.fragments is not None:
                msg.fragments, msg.next_index = None, 0
        for t in self._topics.values():
            if t.current is not None:
                t.current = None
                t.stats.dropped_disconnect += 1
            t.supersede_streak = 0
        self._ack_points.clear()
        self._acked_bytes_total = self._sent_bytes_total
        self._acked_frames_total = self._sent_frames_total
        self._min_rtt.clear()
        self._max_rate.clear()
        self._busy_rate.clear()
        self._held_rate_sample, self._rate_confirmed = None, False
        self._link_rate.clear()
        self._delay_window = float(self.config.initial_window_bytes)
        self._update_limits()

    # -- introspection ------------------------------------------------------------------

    def stats(self, now_s: float | None = None) -> dict[str, object]:
        """A JSON-able snapshot of counters, queues and the window."""
        rtt = self.min_rtt_s(now_s)
        return {
            "topics": {name: vars(t.stats).copy() for name, t in self._topics.items()},
            "no_drop_overflow": self.no_drop_overflow,
            "last_error": self.last_error,
            "no_drop_queued": len(self._qn),
            "no_drop_unacked": self._unacked_no_drop,
            "in_flight_bytes": self.in_flight_bytes,
            "in_flight_frames": self.in_flight_frames,
            "window_bytes": self.window_bytes(),
            "min_rtt_ms": None if rtt is None else rtt * 1e3,
            "last_rtt_ms": None if self._last_rtt_s is None else self._last_rtt_s * 1e3,
            "delivery_rate_Bps": self.delivery_rate_bps(now_s),
            "link_rate_Bps": self._link_rate.value(now_s, 0.0),
            "bdp_bytes": self.bdp_bytes(),
            "rate_cap_bytes": self.rate_cap_bytes(),
            "fragment_bytes": self.fragment_bytes(),
            "whole_frame_bytes": self.whole_frame_bytes(),
        }


def _power_of_two_floor(size: int) -> int:
    """The largest power of two not above *size* (*size* >= 1)."""
    return 1 << (size.bit_length() - 1)
