"""The NATS fan-out: relay replicas share accepted frames through a NATS cluster.

Per accepted frame (:meth:`NatsFanout.publish`): local delivery exactly as in one process,
then the frame (its FlatBuffers bytes, unchanged: no per-frame JSON) joins a bounded
queue that one task hands to the NATS client; the client batches writes in its own
flusher, so nothing here flushes per frame.

Per remote frame: NATS delivers it on the subscription of the subject that covers it, and
the core delivers it to local subscribers only (:meth:`RelayCore.on_remote`), never
publishing it again. Together with ``no_echo`` (NATS does not send a connection its own
publishes) and subscriptions that never overlap (:func:`subjects.cover`), each subscriber
gets a frame once: from its own replica's local delivery or from NATS, not both.

Interest follows subscriptions (:class:`Interest`): a replica subscribes to the subjects
its local consumers' patterns need and unsubscribes when nobody holds them.

Faults: NATS lost while running: local delivery goes on; latest-only frames for other
replicas are dropped (counted ``disconnected``), not buffered into a burst of stale
telemetry; no_drop frames stay queued, in order, within the queue's bounds, and go out
when the client is back (it reconnects by itself and re-subscribes): a NATS node's death
must not lose an event the robot was told was delivered. Every drop is counted in
``fleetctl_cluster_dropped_total{reason}``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Iterable
from typing import Any

import nats
from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.aio.subscription import Subscription
from nats.errors import Error as NatsError

from fleetctl.errors import ConfigError
from fleetctl.server.cluster import kvloops
from fleetctl.server.cluster.config import ClusterConfig, ClusterStartError
from fleetctl.server.cluster.framequeue import (
    FrameQueue,
    Queued,
    SubjectMemo,
    frame_digest,
    queued,
)
from fleetctl.server.cluster.interest import Interest
from fleetctl.server.cluster.remoteinterest import RemoteInterest
from fleetctl.server.cluster.remoteorder import ORDER_HEADER, order_subject
from fleetctl.server.cluster.sharedlatched import SharedLatched
from fleetctl.server.cluster.sharedregistry import SharedRegistry
from fleetctl.server.cluster.sharedsessions import SharedSessions, live_subject
from fleetctl.server.cluster.subjects import (
    MAX_SUBJECT_BYTES,
    SUB_PENDING_BYTES,
    SUB_PENDING_MESSAGES,
    control_subject,
    is_control_subject,
    topic_subject,
)
from fleetctl.server.fanout import LocalFanout, MetricFamily
from fleetctl.wire.errors import WireError

log = logging.getLogger("fleetctl.server.cluster")

# While NATS is away, how often newly queued latest-only frames are shed (bounds how old
# a latest-only frame can be when it goes out after the reconnect).
DISCONNECTED_LOOK_S = 0.1
RECONNECT_WAIT_S = 0.25
# A NATS node whose host died or was cut off sends no FIN: nats-py notices only when its
# pings go unanswered. Its default (2 min x 2 pings) left a replica publishing into a dead
# connection for up to 4 minutes; 2 s x 2 notices within ~6 s and costs one PING a second
# or less per replica.
PING_INTERVAL_S = 2
MAX_OUTSTANDING_PINGS = 2
FLUSH_TIMEOUT_S = 2.0
# A refused change of what a replica reads from the sessions' stream is tried again after
# this (JetStream electing a leader, NATS away).
INTEREST_RETRY_S = 1.0
# Another replica's "cannot read the stream" holds this long (it repeats it every second).
READER_AWAY_HOLD_S = 3.0
# The header of a no_drop frame's core copy: its digest (the stream's Nats-Msg-Id).
DIGEST_HEADER = "Fleetctl-Digest"


class NatsFanout:
    """Local delivery plus publish/subscribe on NATS.

    Args:
        local: The in-process fan-out (local delivery).
        on_remote: Delivers a frame from another replica locally (``RelayCore.on_remote``).
        config: The ``cluster:`` section.
        registry: The shared robot registry, started on this NATS connection once it is
            up and stopped before it closes; ``None`` in tests of the fan-out alone.
        latched: The shared latched messages, likewise.
        on_keyframe_request: Handles another replica's keyframe request (a
            ``KeyframeRequest`` frame; ``firstframes.on_remote_keyframe_request``).
        sessions: The shared sessions (every local no_drop frame is also stored in their
            stream), likewise.
        remote_interest: The replicas' interest: a frame is published only if another
            replica wants it; ``None``: every frame is published.
    """

    def __init__(self, local: LocalFanout, on_remote: Callable[[bytes], None],
                 config: ClusterConfig, registry: SharedRegistry | None = None,
                 latched: SharedLatched | None = None,
                 on_keyframe_request: Callable[[bytes], None] | None = None,
                 sessions: SharedSessions | None = None,
                 remote_interest: RemoteInterest | None = None) -> None:
        self.registry = registry
        self.latched = latched
        self.sessions = sessions
        self.remote_interest = remote_interest
        self.unwanted = 0
        if sessions is not None:
            sessions.on_away = self._publish_live_copies
        self._on_keyframe_request = on_keyframe_request
        self.keyframe_subject = control_subject(config.subject_prefix, "keyframe")
        self._local = local.publish
        self._local_fanout = local
        self._on_remote = on_remote
        self.config = config
        self.interest = Interest(config.subject_prefix)
        self._subject = SubjectMemo(config.subject_prefix, topic_subject)
        self._wake = asyncio.Event()
        self._queue = FrameQueue(config.publish_queue_frames, config.publish_queue_bytes,
                                 self._wake)
        self._back = asyncio.Event()  # set while NATS is connected
        self._interest_changed = asyncio.Event()
        self._nc: Client | None = None
        self._subs: dict[str, Subscription] = {}
        self._control_sub: Subscription | None = None
        self._reader_away_sub: Subscription | None = None
        self._readers_away: dict[str, float] = {}  # replica -> until (monotonic)
        self.replays = 0
        self._tasks: list[asyncio.Task[None]] = []
        self._connecting: asyncio.Task[None] | None = None
        self._last_error: BaseException | None = None
        self._stopping = False
        self.published = 0
        self.received = 0
        self.dropped: dict[str, int] = {}
        self.reconnects = 0

    # -- the Fanout interface ---------------------------------------------------------

    def publish(self, topic: str, frame: bytes, no_drop: bool, message_id: int | None) -> None:
        self._local(topic, frame, no_drop, message_id)
        order: str | None = None
        if no_drop and self.sessions is not None:
            # Other replicas read no_drop frames from the sessions' stream (stored,
            # acknowledged, in order, surviving a NATS node's death); over core NATS
            # too only while the stream is away or another replica cannot read it. The
            # copies carry the frame's digest (a receiver drops the second one) and its
            # order (a receiver delivers in it: remoteorder.py). Why not over core NATS
            # always: measured, it cost more than it saved (docs/scaling.md).
            order = self.sessions.offer(topic, frame, message_id)
            if not self.sessions.stream_away() and not self._a_reader_away():
                return
        subject = self._subject(topic)
        if self.remote_interest is not None and not self.remote_interest.wants(subject):
            self.unwanted += 1  # no other replica has a subscriber for it
            return
        digest = frame_digest(frame) if order is not None else None
        self._enqueue(queued(subject, frame, topic, no_drop, message_id, digest, order))

    def follow(self, pattern: str, delta: int, receive: tuple[str, ...] | None = None) -> None:
        if self.interest.follow(pattern, delta, receive):
            self._interest_changed.set()

    def forward_keyframe_request(self, frame: bytes) -> bool:
        """Publish the request on the control subject every replica listens to (the one
        with the topic's publisher routes it); through the publish queue and its bounds."""
        self._enqueue(queued(self.keyframe_subject, frame, "", False))
        return True

    def _publish_live_copies(self, waiting: list[Queued]) -> None:
        """The sessions' stream went away: the no_drop frames still waiting for it, and
        those stored in the last ``AWAY_RECENT_S``, go out now on core NATS (other
        replicas' viewers, which drop by digest what they had) and to this replica's
        session connections, which skipped them live to get them from the stream (their
        clients drop what they had)."""
        for entry in waiting:
            self._local_fanout.deliver_to_stream_fed(entry.topic, entry.frame,
                                                     entry.message_id)
            self._enqueue(self._core_copy(entry))

    def _core_copy(self, stored: Queued) -> Queued:
        """A frame of the sessions' stream queue as its core NATS copy: its live subject,
        and its digest, by which a receiver drops the stream's copy or this one."""
        return stored._replace(subject=live_subject(self.config, stored.subject),
                               digest=frame_digest(stored.frame))

    def _a_reader_away(self) -> bool:
        """Another replica said it cannot read the stream, within
        :data:`READER_AWAY_HOLD_S`: no_drop frames go to it over core NATS too."""
        away = self._readers_away
        if not away:
            return False
        now = time.monotonic()
        for replica in [r for r, until in away.items() if until < now]:
            del away[replica]
            log.info("replica %s: replica %r reads the no_drop stream again (or is gone): "
                     "no_drop frames through the stream only", self.config.name, replica)
        return bool(away)

    async def _reader_away_received(self, msg: Msg) -> None:
        """Another replica cannot read the stream: send it what it may have missed (the
        last ``HISTORY_S`` of local no_drop frames, which it drops where it has them)
        and the next no_drop frames over core NATS too, while it keeps saying so."""
        try:
            replica = msg.data.decode()
        except UnicodeDecodeError:
            self._drop("malformed")
            return
        if replica == self.config.name or self.sessions is None or len(replica) > 64:
            return  # our own, or not a replica name (config.py: 1-64 characters)
        now = time.monotonic()
        newly = self._readers_away.get(replica, 0.0) < now
        self._readers_away[replica] = now + READER_AWAY_HOLD_S
        if not newly:
            return
        waiting = self.sessions.recent()
        log.warning("replica %s: replica %r cannot read the no_drop stream: sending it the "
                    "last %d no_drop frames and the next ones over core NATS too",
                    self.config.name, replica, len(waiting))
        self.replays += 1
        for entry in waiting:
            copy = self._core_copy(entry)
            if self.remote_interest is None or self.remote_interest.wants(copy.subject):
                self._enqueue(copy)

    def _enqueue(self, entry: Queued) -> None:
        """Queue a frame for the publish task, within the queue's bounds (else counted
        ``queue_full``)."""
        if not self._queue.put(entry):
            self._drop("queue_full")

    async def start(self) -> None:
        """Connect to NATS and start publishing and following interest.

        Raises:
            ClusterStartError: No NATS server answers (names ``cluster.nats_urls``) or
                NATS refuses the credentials (names ``cluster.credentials``).
            ConfigError: The password file cannot be read.
        """
        self._nc = await self._connect()
        self._back.set()
        self._tasks = [asyncio.create_task(self._publish_loop()),
                       asyncio.create_task(self._interest_loop())]
        self._interest_changed.set()  # subscriptions made before start
        if self._on_keyframe_request is not None:
            self._control_sub = await self._nc.subscribe(
                self.keyframe_subject, cb=self._keyframe_request_received)
        if self.sessions is not None:
            self._reader_away_sub = await self._nc.subscribe(
                self.sessions.reader_away_subject, cb=self._reader_away_received)
        try:
            for state in self._shared():
                await state.start(self._nc)
        except BaseException:
            await self.stop()
            raise
        log.info("replica %s joined NATS at %s", self.config.name, self._nc.connected_url
                 and self._nc.connected_url.netloc)

    async def stop(self) -> None:
        self._stopping = True  # our own close is not a lost connection
        for state in reversed(self._shared()):
            await state.stop()
        for task in self._tasks:
            task.cancel()
        if self._tasks:  # bounded: a task that lost its cancellation must not hang a stop
            _, pending = await asyncio.wait(self._tasks, timeout=2.0)
            for task in pending:
                log.warning("replica %s: task %s did not stop within 2 s of its "
                            "cancellation", self.config.name, task.get_coro())
        self._tasks = []
        if self._nc is not None:
            with contextlib.suppress(Exception):
                await self._nc.close()
        self._nc = None

    def metric_families(self) -> Iterable[MetricFamily]:
        return [*(f for state in self._shared() for f in state.metric_families()),
            ("fleetctl_cluster_published_total", "counter",
             "Frames published to other replicas through NATS.", "", {"": self.published}),
            ("fleetctl_cluster_replays_total", "counter",
             "Times another replica could not read the no_drop stream and this one sent "
             "it its recent no_drop frames over core NATS.", "", {"": float(self.replays)}),
            ("fleetctl_cluster_unwanted_total", "counter",
             "Frames not published: no other replica had a subscriber for them.", "",
             {"": float(self.unwanted)}),
            ("fleetctl_cluster_received_total", "counter",
             "Frames received from other replicas through NATS.", "", {"": self.received}),
            ("fleetctl_cluster_dropped_total", "counter",
             "Frames not carried between replicas, by reason.", "reason",
             {k: float(v) for k, v in self.dropped.items()}),
            ("fleetctl_cluster_interest_derived_total", "counter",
             "Local subscriptions (pattern and receive rules) whose NATS subjects were "
             "derived, by what the receive rules did: narrowed, unchanged, unclear (an "
             "alternation not split: subjects may be wider than needed).", "result",
             {k: float(v) for k, v in self.interest.counters.items()}),
            ("fleetctl_cluster_subscriptions", "gauge",
             "NATS subscriptions this replica holds (interest of its consumers).", "",
             {"": float(len(self._subs))}),
            ("fleetctl_cluster_connected", "gauge", "1 while connected to NATS.", "",
             {"": float(self.connected)}),
            ("fleetctl_cluster_reconnects_total", "counter", "Reconnections to NATS.", "",
             {"": float(self.reconnects)}),
        ]

    # -- state -------------------------------------------------------------------------

    def _shared(self) -> list[SharedRegistry | SharedLatched | SharedSessions | RemoteInterest]:
        """The state kept in JetStream, in start order."""
        return [s for s in (self.remote_interest, self.registry, self.latched, self.sessions)
                if s is not None]

    @property
    def connected(self) -> bool:
        return self._nc is not None and self._nc.is_connected

    @property
    def subscribed(self) -> frozenset[str]:
        """Subjects this replica holds a NATS subscription on (may run ahead of the
        server by one round trip)."""
        return frozenset(self._subs)

    def _drop(self, reason: str, n: int = 1) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + n

    # -- connection ---------------------------------------------------------------------

    async def _connect(self) -> Client:
        """Connect within ``connect_timeout_s``; refused credentials fail at once.

        The client retries forever once it has connected (``max_reconnect_attempts=-1``);
        at start it would too, so the attempt runs as a task this bounds.
        """
        config = self.config
        nc = Client()
        attempt = asyncio.create_task(nc.connect(
            servers=list(config.nats_urls), name=config.name, no_echo=True,
            connect_timeout=config.connect_timeout_s,  # type: ignore[arg-type]
            allow_reconnect=True, max_reconnect_attempts=-1, dont_randomize=True,
            reconnect_time_wait=RECONNECT_WAIT_S,  # type: ignore[arg-type]
            ping_interval=PING_INTERVAL_S, max_outstanding_pings=MAX_OUTSTANDING_PINGS,
            skip_subject_validation=True,
            error_cb=self._on_error, disconnected_cb=self._on_disconnected,
            reconnected_cb=self._on_reconnected, **self._credentials()))
        self._connecting = attempt
        try:
            await asyncio.wait({attempt}, timeout=config.connect_timeout_s)
        finally:
            self._connecting = None
        if attempt.done() and not attempt.cancelled() and attempt.exception() is None:
            return nc
        attempt.cancel()
        with contextlib.suppress(BaseException):
            await attempt
        self._stopping = True  # the close below is not a lost connection
        with contextlib.suppress(Exception):
            await nc.close()
        failure = self._last_error or (attempt.exception() if attempt.done()
                                       and not attempt.cancelled() else None)
        raise _start_error(config, failure)

    def _credentials(self) -> dict[str, Any]:
        creds = self.config.credentials
        if creds is None:
            return {}
        if creds.creds_file is not None:
            return {"user_credentials": str(creds.creds_file)}
        if creds.nkey_seed_file is not None:
            return {"nkeys_seed": str(creds.nkey_seed_file)}
        try:
            return {"user": creds.user, "password": creds.read_password()}
        except (OSError, IndexError, UnicodeError) as exc:
            raise ConfigError(f"field 'cluster.credentials.password_file': cannot read "
                              f"{creds.password_file}: "
                              f"{getattr(exc, 'strerror', None) or type(exc).__name__}") from None

    async def _on_error(self, exc: Exception) -> None:
        if isinstance(exc, nats.errors.SlowConsumerError):
            self._drop("slow_consumer")
            return
        if self._connecting is not None:  # at start: the reason the start error gives
            self._last_error = exc
            if _refused(exc):
                self._connecting.cancel()
            return
        log.warning("replica %s: NATS: %s", self.config.name, _reason(exc))

    async def _on_disconnected(self) -> None:
        if self._stopping or self._connecting is not None:
            return
        self._back.clear()
        if self.sessions is not None:
            self.sessions.stream_away()  # now, not at the next no_drop frame: pongs go
        log.warning("replica %s: NATS connection lost: local delivery goes on; latest-only "
                    "frames for other replicas are dropped, no_drop ones held (bounded) "
                    "until it is back", self.config.name)

    async def _on_reconnected(self) -> None:
        self.reconnects += 1
        nc = self._nc
        url = nc.connected_url.netloc if nc is not None and nc.connected_url else "?"
        self._back.set()
        log.info("replica %s: NATS reconnected to %s", self.config.name, url)
        self._interest_changed.set()  # in case a change failed while it was away

    # -- tasks --------------------------------------------------------------------------

    async def _publish_loop(self) -> None:
        queue, wake = self._queue, self._wake
        while True:
            if not queue:
                wake.clear()
                await wake.wait()
            nc = self._nc
            assert nc is not None
            if not nc.is_connected:
                self._shed_latest_only()
                # Until it is back; new frames meanwhile are shed at the next look.
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(DISCONNECTED_LOOK_S):
                        await self._back.wait()
                continue
            await self._publish_some(nc, queue)

    def _shed_latest_only(self) -> None:
        """NATS is away: drop the latest-only frames (stale telemetry is never replayed
        late), keep the no_drop ones in order for when it is back."""
        shed = self._queue.keep(lambda entry: entry.no_drop)
        if shed:
            self._drop("disconnected", shed)

    async def _publish_some(self, nc: Client, queue: FrameQueue) -> None:
        # The client appends to its pending buffer; its flusher writes in batches.
        for _ in range(min(len(queue), 1024)):
            entry = queue.popleft()
            subject, frame = entry.subject, entry.frame
            if len(subject) > MAX_SUBJECT_BYTES:
                self._drop("subject_too_long")
                continue
            try:
                if entry.digest is None:
                    await nc.publish(subject, frame)
                else:  # a no_drop frame's core copy: receivers drop a second copy by it
                    headers = {DIGEST_HEADER: entry.digest}
                    if entry.order is not None:
                        headers[ORDER_HEADER] = entry.order
                    await nc.publish(subject, frame, headers=headers)
            except NatsError:  # lost between the check and now, or a too-large payload
                self._drop("publish_failed")
                continue
            self.published += 1
        await asyncio.sleep(0)  # let the relay read its sockets between batches

    async def _interest_loop(self) -> None:
        while True:
            kvloops.raise_if_cancelled()  # a cancellation a NATS request swallowed
            await self._interest_changed.wait()
            self._interest_changed.clear()
            try:
                await self._follow_interest()
            except NatsError as exc:  # closed under us: the next change or reconnect retries
                log.warning("replica %s: NATS subscriptions not updated: %s",
                            self.config.name, _reason(exc))
                subscribed = False
            else:
                subscribed = True
            followed = (self.sessions is None
                        or await self.sessions.follow_interest(self.interest.wanted))
            if subscribed and self.remote_interest is not None:
                # Subscribed, and reading the stream's subjects too (or failing to, then
                # announced anyway: live data first): the others may publish. After the
                # reader, so that the stream copy of every core copy of a no_drop frame
                # comes here too, and the order stage is told when to let it go.
                self.remote_interest.announce(self.interest.wanted)
            if not followed:
                await asyncio.sleep(INTEREST_RETRY_S)  # a retry pace, not a synchronization
                self._interest_changed.set()

    async def _follow_interest(self) -> None:
        nc = self._nc
        assert nc is not None
        wanted = self.interest.wanted
        for subject in [s for s in wanted if s not in self._subs]:
            self._subs[subject] = await nc.subscribe(
                subject, cb=self._receiver(subject), pending_msgs_limit=SUB_PENDING_MESSAGES,
                pending_bytes_limit=SUB_PENDING_BYTES)
        for subject in [s for s in self._subs if s not in wanted]:
            sub = self._subs.pop(subject)
            with contextlib.suppress(NatsError):
                await sub.unsubscribe()
        # A round trip, so the server holds the new interest once this returns (other
        # servers of the cluster learn it over their routes a moment later).
        with contextlib.suppress(NatsError, asyncio.TimeoutError):
            await nc.flush(timeout=FLUSH_TIMEOUT_S)  # type: ignore[arg-type]

    async def _keyframe_request_received(self, msg: Msg) -> None:
        assert self._on_keyframe_request is not None
        try:
            self._on_keyframe_request(msg.data)
        except WireError:
            self._drop("malformed")

    def _receiver(self, subject: str) -> Callable[[Msg], Any]:
        async def receive(msg: Msg) -> None:
            # Only the subscription of a subject still wanted delivers: while a wider one
            # replaces narrower ones, the old ones' messages would be duplicates.
            if subject not in self.interest.wanted:
                return
            if is_control_subject(self.config.subject_prefix, msg.subject):
                return  # a wide subscription hears the replicas' control subjects too
            headers, sessions = msg.headers, self.sessions
            if headers and sessions is not None:  # a no_drop frame: it comes twice
                if not sessions.first_copy(headers.get(DIGEST_HEADER)):
                    return  # the stream brought it already
                self.received += 1
                sessions.remote_order.offer(headers.get(ORDER_HEADER),
                                            order_subject(msg.subject), msg.data)
                return
            self.received += 1
            try:
                self._on_remote(msg.data)
            except WireError:
                self._drop("malformed")

        return receive


def _reason(exc: BaseException) -> str:
    return str(exc) or type(exc).__name__


def _refused(exc: BaseException) -> bool:
    reason = _reason(exc).lower()
    return isinstance(exc, nats.errors.AuthorizationError) or "authorization" in reason \
        or "authentication" in reason


def _start_error(config: ClusterConfig, exc: BaseException | None) -> ClusterStartError:
    urls = ", ".join(config.nats_urls)
    reason = "no answer" if exc is None else _reason(exc)
    if exc is not None and _refused(exc):
        log.error("replica %s: NATS at %s refused its credentials: %s", config.name, urls,
                  reason)
        return ClusterStartError(f"field 'cluster.credentials': NATS at {urls} refused replica "
                           f"{config.name!r}: {reason}")
    return ClusterStartError(f"field 'cluster.nats_urls': cannot reach NATS at {urls} within "
                       f"{config.connect_timeout_s:g} s: {reason}")
