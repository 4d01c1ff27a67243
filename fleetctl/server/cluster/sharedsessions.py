"""Named sessions shared by relay replicas: records in JetStream KV, no_drop frames in a
JetStream stream (issue 15; docs/scaling.md, "Sessions").

Why: a session's mailbox used to live in the memory of the replica its connection was
on; when that replica died, so did what the session had missed. In a cluster nothing of a
session lives only in one replica:

- **Every no_drop frame** a replica accepts from a local sender is also published to the
  stream ``<prefix>_nodrop`` (subjects ``<prefix>_nd.<topic as subject>``), with a
  ``Nats-Msg-Id`` of the frame's digest, so a robot's resend of the same frame through
  another replica is stored once. Retention: ``session_expiry_s``, at most
  ``cluster.session_stream_bytes``, oldest out first.
- **Every session** is a record in the KV bucket ``<prefix>_sessions``
  (:mod:`~fleetctl.server.cluster.sessionrecord`): its patterns, its cursor in the
  stream, the replica that holds its connection. Records expire ``session_expiry_s`` after
  their last write; the holding replica rewrites its records at least every
  :data:`REFRESH_S`.
- **A session's connection** gets its no_drop frames from the stream
  (:class:`~fleetctl.server.cluster.sessionfeed.SessionFeed`), after the record's
  cursor, never from the live fan-out: resumed on any replica, it gets what it missed, in
  stream order, then the live frames.
- **Takeover**: attaching writes the record unconditionally (the newest connection wins,
  as on one server); every later write of the replica is conditional on its own last
  revision. A replica that sees its session written by another one (the watch, or a
  refused conditional write) closes its connection with 4409.

Per-frame cost: droppable frames pay nothing; a no_drop frame pays one JetStream publish
(acknowledged, up to 64 out at once: streamstores.py) and, per attached session on any
replica, one stream delivery.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import logging
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from nats.aio.client import Client
from nats.errors import Error as NatsError
from nats.errors import MaxPayloadError
from nats.js import JetStreamContext, api
from nats.js.errors import APIError, KeyWrongLastSequenceError, ServiceUnavailableError
from nats.js.errors import Error as JetStreamError
from nats.js.kv import KeyValue

from fleetctl.server.cluster import kvloops
from fleetctl.server.cluster.config import ClusterConfig, ClusterStartError
from fleetctl.server.cluster.framequeue import (
    FrameQueue,
    Queued,
    RecentDigests,
    SubjectMemo,
    frame_digest,
    queued,
)
from fleetctl.server.cluster.remotefeed import RemoteFeed
from fleetctl.server.cluster.remoteorder import (
    ORDER_HEADER,
    ReceiverOrder,
    SenderOrder,
    covered_by,
)
from fleetctl.server.cluster.sessionfeed import SessionFeed
from fleetctl.server.cluster.sessionrecord import (
    SessionKey,
    SessionRecord,
    decode_record,
    encode_record,
    parse_record_key,
    record_key,
)
from fleetctl.server.cluster.storeacks import StoreAcks
from fleetctl.server.cluster.streamstores import StreamStores
from fleetctl.server.cluster.subjects import (
    MAX_SUBJECT_BYTES,
    control_subject,
    cover,
    pattern_subject,
    topic_subject,
)
from fleetctl.server.fanout import MetricFamily
from fleetctl.server.regex import BadRegex, compile_full
from fleetctl.wire.errors import WireError

if TYPE_CHECKING:
    from fleetctl.server.outbound import OutboundScheduler

log = logging.getLogger("fleetctl.server.cluster")

# A held session's record is rewritten at least this often (its bucket's TTL is the
# session expiry, an hour by default).
REFRESH_S = 60.0
# How often cursors and pattern changes are written (a crash replays at most about this
# much, which the clients drop as duplicates).
WRITE_S = 0.5
RETRY_S = 1.0
# Frames out to the stream at once, waiting for their acknowledgement (each is published
# as soon as it is queued and there is room: streamstores.py).
STORES_IN_FLIGHT = 64
# An acknowledged store: milliseconds normally; a request lost in a NATS node's dead socket
# is retried after this (the frames behind it wait, in order).
STORE_TIMEOUT_S = 1.0
STORE_RETRY_S = 0.25
# Which replica stored a frame (each replica skips its own when reading the stream).
REPLICA_HEADER = "Fleetctl-Replica"
DUPLICATE_WINDOW_S = 120.0
# What a replica keeps of its local senders' no_drop frames to send again over core NATS
# when another replica says it cannot read the stream (covers that replica's detection,
# about 1-2 s, many times over).
HISTORY_S = 10.0
HISTORY_BYTES = 8 * 1024 * 1024
HISTORY_FRAMES = 65536
# When the stream goes away, the frames stored in the last this many seconds go out again
# with those waiting (a reader on the dying NATS node may not have handed them on; its
# deliveries lag a store by milliseconds). Short: this replica's own session connections
# get them too, into their bounded no_drop queues.
AWAY_RECENT_S = 2.0
# How often a replica checks that its reader of the stream is alive.
READER_CHECK_S = 1.0


def stream_name(config: ClusterConfig) -> str:
    return f"{config.subject_prefix}_nodrop"


def stream_root(config: ClusterConfig) -> str:
    """The first token of the stream's subjects (apart from the live ones, so that a
    replica subscribed to ``<prefix>.>`` does not hear them)."""
    return f"{config.subject_prefix}_nd"


def bucket_name(config: ClusterConfig) -> str:
    return f"{config.subject_prefix}_sessions"


def live_subject(config: ClusterConfig, stream_subject: str) -> str:
    """The core NATS subject of a frame stored on *stream_subject*."""
    return config.subject_prefix + stream_subject[len(stream_root(config)):]


def session_subjects(root: str, patterns: Iterable[str]) -> tuple[str, ...]:
    """The stream subjects a session's consumer reads: each pattern's subject (as
    interest maps it, under *root*), none covering another; empty without patterns."""
    subjects = []
    for pattern in patterns:
        try:
            literal = compile_full(pattern).literal
        except BadRegex:  # a hostile record's pattern: refused when resubscribed
            continue
        subjects.append(pattern_subject(root, pattern, literal))
    return tuple(sorted(cover(subjects)))


@dataclass
class _Held:
    """A session whose record this replica writes."""

    patterns: dict[str, None]  # the session's own (live) pattern dict
    since: float
    cursor: int | None
    revision: int | None  # of the record this replica's state is based on
    feed: SessionFeed | None = None
    task: asyncio.Task[None] | None = None
    resubscribe: asyncio.Event = field(default_factory=asyncio.Event)
    attached: bool = True
    fresh_attach: bool = True  # the attach itself is not written yet
    ended: bool = False
    written_s: float = 0.0
    written_cursor: int | None = None
    dirty: bool = True
    on_taken: Callable[[], None] | None = field(default=None, repr=False)


class SharedSessions:
    """The replica's side of shared sessions.

    Args:
        config: This replica's cluster section.
        expiry_s: ``session_expiry_s``: how long a record and a stored frame live.
        on_remote: Delivers another replica's no_drop frame from the stream to this
            replica's connections without a session (``RelayCore.on_remote``); ``None``:
            only sessions read the stream (tests).
        clock: Wall clock in seconds (a new session's start, record age).
    """

    def __init__(self, config: ClusterConfig, expiry_s: float,
                 on_remote: Callable[[bytes], None] | None = None,
                 clock: Callable[[], float] = time.time) -> None:
        self.config = config
        self.expiry_s = expiry_s
        self._clock = clock
        self._stream = stream_name(config)
        self._root = stream_root(config)
        self._records: dict[SessionKey, tuple[SessionRecord, int, float]] = {}
        self._held: dict[SessionKey, _Held] = {}
        self._publish_wake = asyncio.Event()
        self._queue = FrameQueue(config.publish_queue_frames, config.publish_queue_bytes,
                                 self._publish_wake)
        self._subject = SubjectMemo(self._root, topic_subject)
        self._write_wake = asyncio.Event()
        self._js: JetStreamContext | None = None
        self._nc: Client | None = None
        self._storing_fails = False
        self._away_noted = False
        # Which no_drop frames are stored: a local sender's pong waits for its frames.
        self.acks = StoreAcks()
        # Called with the recent frames and those still waiting for the stream when it
        # goes away (NATS lost, or storing starts to fail): the fan-out sends them over
        # core NATS too and to this replica's session connections, which skipped them
        # live (other replicas' viewers and these would otherwise wait for the stream,
        # lose them with this replica, or get a stored one after a later live one when
        # their reader died with the same NATS node); receivers drop what they had.
        self.on_away: Callable[[list[Queued]], None] | None = None
        self._purged_s = 0.0
        self._kv: KeyValue | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._feed_stops: set[asyncio.Task[None]] = set()
        self.counters = {"stored": 0, "duplicates": 0, "store_failures": 0, "refused": 0,
                         "queue_full": 0, "subject_too_long": 0, "puts": 0,
                         "put_failures": 0, "deletes": 0, "taken_over": 0, "malformed": 0,
                         "feed_failures": 0, "delivered": 0, "follow_failures": 0,
                         "reader_away": 0, "remote_duplicates": 0}
        self._stores = StreamStores(self._stream, STORES_IN_FLIGHT, STORE_TIMEOUT_S,
                                    self._acknowledged, self.counters)
        self._store_failure: BaseException | None = None  # the oldest store's, to retry
        self._history: deque[tuple[float, Queued]] = deque()
        self._history_bytes = 0
        self.recent_remote = RecentDigests()
        self.reader_away_subject = control_subject(config.subject_prefix, "readeraway")
        # This replica's no_drop frames carry their order; others' are delivered in theirs.
        self.order = SenderOrder()
        self._on_remote = on_remote
        self.remote_order = ReceiverOrder(self._deliver_remote, self.counters)
        self._remote = RemoteFeed(self._stream, config.subject_prefix, self._root,
                                  config.name, REPLICA_HEADER, self.remote_order.offer_stream,
                                  self.counters, self.first_copy) \
            if on_remote is not None else None
        self._wanted: frozenset[str] = frozenset()
        self._following = False

    # -- life cycle -----------------------------------------------------------------------

    async def start(self, nc: Client) -> None:
        """Create (or update) the stream and the bucket, load the records, start the
        tasks.

        Raises:
            ClusterStartError: JetStream refuses the stream or the bucket (names the field).
        """
        self._nc = nc
        self._js = js = nc.jetstream()
        stream = api.StreamConfig(
            name=self._stream, subjects=[f"{self._root}.>"],
            retention=api.RetentionPolicy.LIMITS, discard=api.DiscardPolicy.OLD,
            max_age=self.expiry_s, max_bytes=self.config.session_stream_bytes,
            storage=api.StorageType.FILE, num_replicas=self.config.state_replicas,
            duplicate_window=min(DUPLICATE_WINDOW_S, self.expiry_s))
        try:
            try:
                await kvloops.while_electing(lambda: js.add_stream(stream))
            except APIError:  # it exists with other limits: take this replica's config
                await kvloops.while_electing(lambda: js.update_stream(stream))
        except (TimeoutError, JetStreamError) as exc:
            raise ClusterStartError(
                f"field 'cluster.state_replicas': cannot create the sessions' JetStream "
                f"stream {self._stream!r} with {self.config.state_replicas} replica(s): "
                f"{exc!r}") from exc
        self._kv = await kvloops.open_bucket(nc, self.config, bucket_name(self.config),
                                             "the sessions'", ttl=self.expiry_s)
        watcher = await self._kv.watchall()
        if self._remote is not None:
            remote = self._remote
            self._following = True  # interest changes from now on follow too (serialized)
            await kvloops.while_electing(lambda: remote.follow(js, self._wanted))
        self._tasks = [asyncio.create_task(self._watch(watcher)),
                       asyncio.create_task(self._write_loop()),
                       asyncio.create_task(self._publish_loop()),
                       asyncio.create_task(self._check_reader())]
        self._publish_wake.set()

    async def stop(self) -> None:
        """Write the held sessions' cursors (best effort), stop every feed and task."""
        self.acks.release_all()  # nothing will be stored any more: no pong waits
        self.remote_order.close()  # frames held for a missing one go now
        for held in self._held.values():
            if held.task is not None:
                held.task.cancel()
        await kvloops.stop(self.write_due, self._tasks)
        if self._remote is not None:
            await self._remote.stop()
        for held in list(self._held.values()):
            if held.feed is not None:
                await held.feed.stop()
        if self._feed_stops:
            await asyncio.wait(set(self._feed_stops), timeout=2.0)
        self._tasks = []

    # -- what the session table asks --------------------------------------------------------

    def lookup(self, key: SessionKey) -> SessionRecord | None:
        """The session's record (held here or from the bucket), ``None`` if there is none
        or it expired."""
        held = self._held.get(key)
        if held is not None and not held.ended:
            return SessionRecord(tuple(held.patterns), held.cursor, held.since,
                                 self.config.name if held.attached else None)
        entry = self._records.get(key)
        if entry is None:
            return None
        record, _, written_s = entry
        if self._clock() - written_s > self.expiry_s:
            del self._records[key]
            return None
        return record

    def count(self, identities: tuple[str, ...]) -> int:
        """Sessions of *identities* the replicas know of (expired ones not counted)."""
        keys = {k for k in list(self._records)
                if k[0] == identities and self.lookup(k) is not None}
        keys.update(k for k, h in self._held.items() if k[0] == identities and not h.ended)
        return len(keys)

    def attach(self, key: SessionKey, patterns: dict[str, None], outbound: OutboundScheduler,
               wants: Callable[[str], bool], is_open: Callable[[], bool],
               on_taken: Callable[[], None]) -> SessionFeed:
        """A connection attached to session *key* here: start its feed after the record's
        cursor (or from now, for a new session) and write the record with this replica as
        its owner. Returns the feed."""
        previous = self._held.pop(key, None)
        if previous is not None:
            self._stop_feed(previous)
        record = self.lookup(key) if previous is None else SessionRecord(
            (), previous.cursor, previous.since, None)
        entry = self._records.get(key)
        held = _Held(patterns=patterns,
                     since=record.since if record is not None else self._clock(),
                     cursor=record.cursor if record is not None else None,
                     revision=previous.revision if previous is not None
                     else (entry[1] if entry is not None else None),
                     on_taken=on_taken)
        held.feed = feed = SessionFeed(outbound, wants, is_open, held.cursor, held.since,
                                       self._count_malformed, self.stream_away)
        held.resubscribe.set()
        held.task = asyncio.create_task(self._run_feed(held))
        self._held[key] = held
        self._write_wake.set()
        return feed

    def stream_away(self) -> bool:
        """NATS is lost, or storing in the stream fails: sessions' connections get local
        no_drop frames live meanwhile (docs/scaling.md, "Sessions")."""
        nc = self._nc
        away = self._storing_fails or nc is None or not nc.is_connected
        if away != self._away_noted:
            self._away_noted = away
            self.acks.set_bypass(away)  # nothing waits for a store while it is away
            if away and self.on_away is not None:
                # Before the frame being delivered now goes out live: the recent ones go
                # first, in order (those not stored yet, and those stored lately, which
                # a reader on the same dying NATS node may never have handed on).
                self.on_away(self.recent_and_waiting(AWAY_RECENT_S))
        return away

    def recent_and_waiting(self, seconds: float) -> list[Queued]:
        """The frames offered in the last *seconds*, then every frame still waiting for
        the stream that those do not include; oldest first, each once."""
        waiting = {id(entry) for entry in self._queue}
        before = []
        for entry in self.recent(seconds):
            if id(entry) in waiting:
                break
            before.append(entry)
        return before + list(self._queue)

    def changed(self, key: SessionKey) -> None:
        """The held session's patterns changed."""
        held = self._held.get(key)
        if held is not None:
            held.dirty = True
            held.resubscribe.set()
            self._write_wake.set()

    def detach(self, key: SessionKey, ended: bool) -> None:
        """The held session's connection is gone: stop its feed; write it offline at the
        last acknowledged frame, or delete it when *ended* (no pattern left)."""
        held = self._held.get(key)
        if held is None:
            return
        if held.feed is not None:
            held.cursor = held.feed.settle()
        self._stop_feed(held)
        held.attached = False
        held.ended = ended
        held.dirty = True
        self._write_wake.set()

    def offer(self, topic: str, frame: bytes, message_id: int | None = None) -> str:
        """Store a no_drop frame a local sender sent (queued, bounded, counted), and keep
        it for :meth:`recent`; return its ``Fleetctl-Order`` (its core copy carries it
        too). Per-frame cost matters here (every no_drop frame of every local sender): no
        digest yet (the store makes it), the history pruned by size only (by age when
        read)."""
        subject = self._subject(topic)
        order = self.order.stamp(subject)  # any key unique per subject: the stream's
        entry = queued(subject, frame, topic, True, message_id, None, order)
        if not self._queue.put(entry):
            self.counters["queue_full"] += 1
            return order
        self.acks.note_offered()
        if self._stores.has_room():
            self._publish_wake.set()  # published now, not once the frames out are acked
        history = self._history
        history.append((time.monotonic(), entry))
        self._history_bytes += len(frame)
        if self._history_bytes > HISTORY_BYTES or len(history) > HISTORY_FRAMES:
            self._history_bytes -= len(history.popleft()[1].frame)
        return order

    def _deliver_remote(self, frame: bytes) -> None:
        """Another replica's no_drop frame, in its order, to this replica's connections."""
        assert self._on_remote is not None
        try:
            self._on_remote(frame)
        except WireError:
            self.counters["malformed"] += 1

    def recent(self, seconds: float = HISTORY_S) -> list[Queued]:
        """The no_drop frames local senders sent in the last *seconds* (at most
        :data:`HISTORY_S`, :data:`HISTORY_BYTES`), oldest first: what a replica that
        could not read the stream may have missed."""
        now = time.monotonic()
        return [entry for t, entry in self._history if now - t <= seconds]

    def trim_history(self) -> None:
        """Drop what is older than :data:`HISTORY_S` (the store loop calls it)."""
        history, now = self._history, time.monotonic()
        while history and now - history[0][0] > HISTORY_S:
            self._history_bytes -= len(history.popleft()[1].frame)

    def first_copy(self, digest: str | None) -> bool:
        """Whether another replica's no_drop frame with *digest* is new here (it may come
        twice: over core NATS while a stream reader is away, and from the stream)."""
        if digest is None or self.recent_remote.first(digest):
            return True
        self.counters["remote_duplicates"] += 1
        return False

    # -- feeds ----------------------------------------------------------------------------

    async def _run_feed(self, held: _Held) -> None:
        """Keep *held*'s consumer on the subjects of its patterns: (re)create it when they
        change, none while it has none; retry while NATS refuses (the connection waits)."""
        feed = held.feed
        assert feed is not None
        while True:
            await held.resubscribe.wait()
            held.resubscribe.clear()
            subjects = session_subjects(self._root, held.patterns)
            if subjects == feed.subjects:
                continue
            await feed.stop()
            if not subjects:
                continue
            js = self._js
            if js is not None:
                try:
                    await feed.start(js, self._stream, subjects)
                    continue
                except (TimeoutError, NatsError) as exc:
                    kvloops.raise_if_cancelled()
                    self.counters["feed_failures"] += 1
                    if self.counters["feed_failures"] == 1:
                        log.warning("replica %s: cannot read the sessions' stream: %r; "
                                    "retrying every %.0f s", self.config.name, exc, RETRY_S)
            await asyncio.sleep(RETRY_S)  # a retry pace, not a synchronization
            held.resubscribe.set()

    def _stop_feed(self, held: _Held) -> None:
        if held.task is not None:
            held.task.cancel()
            held.task = None
        feed, held.feed = held.feed, None
        if feed is not None:
            self.counters["delivered"] += feed.delivered
            if feed.running:
                task = asyncio.create_task(feed.stop())
                self._feed_stops.add(task)  # keeps it referenced until done
                task.add_done_callback(self._feed_stops.discard)

    def _count_malformed(self) -> None:
        self.counters["malformed"] += 1

    # -- the bucket ------------------------------------------------------------------------

    async def _watch(self, watcher: KeyValue.KeyWatcher) -> None:
        async for entry in watcher:
            if entry is None:
                continue
            self.on_entry(entry.key, entry.value, entry.operation, entry.revision or 0,
                          entry.created)

    def on_entry(self, name: str, value: bytes | None, operation: str | None,
                 revision: int, created: datetime.datetime | None) -> None:
        """One bucket entry: mirror it; a held session written by another replica is
        taken over."""
        try:
            key = parse_record_key(name)
        except ValueError:
            self.counters["malformed"] += 1
            return
        if operation in ("DEL", "PURGE") or not value:
            self._records.pop(key, None)
            record = None
        else:
            try:
                record = decode_record(value)
            except ValueError:
                self.counters["malformed"] += 1
                return
            written_s = created.timestamp() if created is not None else self._clock()
            self._records[key] = (record, revision, written_s)
        held = self._held.get(key)
        if held is None or held.revision == revision:
            return
        if held.attached and not held.fresh_attach and (
                record is None or record.owner != self.config.name):
            self._taken(key, held)

    def _taken(self, key: SessionKey, held: _Held) -> None:
        """Another replica wrote the session we hold: its connection there is newer."""
        if self._held.get(key) is not held:
            return  # already let go (the watch and a refused write both tell)
        self.counters["taken_over"] += 1
        self._stop_feed(held)
        self._held.pop(key, None)
        if held.attached and held.on_taken is not None:
            held.on_taken()

    async def _write_loop(self) -> None:
        async def tick() -> None:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._write_wake.wait(), WRITE_S)
            self._write_wake.clear()

        await kvloops.write_forever(tick, self.write_due, self.counters, "shared sessions",
                                    RETRY_S)

    async def write_due(self) -> int:
        """Write every held session whose record changed (patterns, cursor, owner) or is
        due for a refresh; return how many writes succeeded."""
        kv = self._kv
        if kv is None:
            return 0
        now = self._clock()
        if now - self._purged_s >= REFRESH_S:  # the bucket's TTL removes them silently
            self._purged_s = now
            for key in [k for k, (_, _, t) in self._records.items() if now - t > self.expiry_s]:
                del self._records[key]
        done = 0
        for key, held in list(self._held.items()):
            if self._held.get(key) is not held:
                continue  # let go while an earlier write was under way
            if held.feed is not None:
                held.cursor = held.feed.settle()
            if not (held.dirty or held.cursor != held.written_cursor
                    or now - held.written_s >= REFRESH_S):
                continue
            try:
                await self._write_one(kv, key, held, now)
                done += 1
            except KeyWrongLastSequenceError:
                self._taken(key, held)
            except (TimeoutError, NatsError):
                kvloops.raise_if_cancelled()
                self.counters["put_failures"] += 1
        return done

    async def _write_one(self, kv: KeyValue, key: SessionKey, held: _Held, now: float) -> None:
        name = record_key(key)
        held.dirty = False
        if held.ended:
            await kv.delete(name, last=held.revision)
            self.counters["deletes"] += 1
            self._forget(key, held)
            return
        attached = held.attached  # it may detach while the write is under way
        record = SessionRecord(tuple(held.patterns), held.cursor, held.since,
                               self.config.name if attached else None)
        value = encode_record(record)
        if attached and held.fresh_attach:
            revision = await kv.put(name, value)  # the newest connection wins
            held.fresh_attach = False
        elif held.revision is None:
            revision = await kv.create(name, value)
        else:
            revision = await kv.update(name, value, last=held.revision)
        self.counters["puts"] += 1
        held.revision = revision
        held.written_s = now
        held.written_cursor = record.cursor
        self._records[key] = (record, revision, now)
        if not attached and not held.dirty:  # written offline, nothing newer: the
            self._forget(key, held)          # bucket holds it now

    def _forget(self, key: SessionKey, held: _Held) -> None:
        if self._held.get(key) is held:
            del self._held[key]
        if held.ended:
            self._records.pop(key, None)

    # -- the stream ------------------------------------------------------------------------

    async def _publish_loop(self) -> None:
        """Store the queued frames in order: each is published as soon as it is queued
        and fewer than ``STORES_IN_FLIGHT`` wait for their acknowledgement
        (:mod:`~fleetctl.server.cluster.streamstores`); it leaves the queue when its own
        acknowledgement (or its refusal) is taken, oldest first (:meth:`_acknowledged`,
        in the acknowledgement's callback: no task switch per frame)."""
        queue, wake, stores = self._queue, self._publish_wake, self._stores
        nc = self._nc
        assert nc is not None
        await stores.start(nc)
        try:
            while True:
                wake.clear()
                failure = self._store_failure
                if failure is not None:
                    self._store_failure = None
                    await self._store_failed(failure)
                    continue
                launched = False
                while (stores.has_room() and len(stores) < len(queue)
                       and self._store_failure is None):
                    await self._send_store(nc, queue[len(stores)])
                    launched = True
                if self._retire() or launched:
                    continue
                if not queue:
                    self.trim_history()
                wait_s = stores.wait_s()
                if wait_s is None:
                    await wake.wait()
                else:  # the oldest frame out times out then
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(wait_s):
                            await wake.wait()
        finally:
            await stores.stop()

    def _retire(self) -> bool:
        """Take the finished stores off the queue, oldest first; ``True`` when the
        oldest failed in a way worth retrying (left to the publish loop). Nothing more
        is retired until the loop has handled that failure: the failed frame is still
        the queue's first, and everything after it is sent again."""
        if self._store_failure is not None:
            return True
        stores = self._stores
        while True:
            finished, result = stores.oldest()
            if not finished:
                return False
            if _transient(result):
                self._store_failure = result
                return True
            self._stored_one(result)

    def _acknowledged(self) -> None:
        """A store was acknowledged: retire what is finished; wake the publish loop
        only when it has something to do (a failure, or frames waiting for room)."""
        if self._retire() or (len(self._queue) > len(self._stores)
                              and self._stores.has_room()):
            self._publish_wake.set()

    async def _send_store(self, nc: Client, entry: Queued) -> None:
        if len(entry.subject) > MAX_SUBJECT_BYTES:
            self.counters["subject_too_long"] += 1
            self._stores.skip()
            return
        headers = {"Nats-Msg-Id": frame_digest(entry.frame),
                   REPLICA_HEADER: self.config.name}
        if entry.order is not None:
            headers[ORDER_HEADER] = entry.order
        await self._stores.send(nc, entry.subject, entry.frame, headers)

    async def _store_failed(self, result: BaseException | None) -> None:
        """The oldest frame's store failed for a reason worth retrying: every frame
        waiting goes out live meanwhile, and after a pause all of them are sent again
        from that frame, in order (JetStream drops a second copy by ``Nats-Msg-Id``)."""
        self.counters["store_failures"] += 1
        if not self._storing_fails:
            log.warning("replica %s: cannot store no_drop frames for sessions (%r): held "
                        "in order, sessions here get them live meanwhile",
                        self.config.name, result)
        self._storing_fails = True
        self.stream_away()  # the frames waiting go out live now
        self._stores.forget()
        await asyncio.sleep(STORE_RETRY_S)  # keep the rest, in order

    def _stored_one(self, result: BaseException | None) -> None:
        """The oldest frame's store is finished with: stored, or refused for good."""
        if self._storing_fails:
            log.info("replica %s: storing no_drop frames for sessions again",
                     self.config.name)
        self._storing_fails = False
        subject, frame = self._queue.popleft()[:2]
        self.acks.note_done()
        if result is not None:
            self.counters["refused"] += 1
            log.warning("replica %s: the sessions' stream refused a frame on %s (%d bytes): "
                        "%r", self.config.name, subject, len(frame), result)

    # -- other replicas' no_drop frames ----------------------------------------------------

    async def follow_interest(self, wanted: frozenset[str]) -> bool:
        """Read other replicas' no_drop frames on the live subjects *wanted* (this
        replica's interest), from now on (:class:`~fleetctl.server.cluster.remotefeed.
        RemoteFeed`); remembered until the stream is set up.

        Returns:
            ``False`` if NATS or JetStream refused (logged once, counted
            ``follow_failures``; the caller tries again).
        """
        if wanted != self._wanted:  # a subject followed again starts afresh
            self.remote_order.forget(covered_by(wanted))
        self._wanted = wanted
        if self._remote is None or self._js is None or not self._following:
            return True
        try:
            await self._remote.follow(self._js, wanted)
        except (TimeoutError, NatsError) as exc:
            kvloops.raise_if_cancelled()
            self.counters["follow_failures"] += 1
            if self.counters["follow_failures"] == 1:
                log.warning("replica %s: cannot follow other replicas' no_drop frames in "
                            "the sessions' stream: %r; retrying", self.config.name, exc)
            return False
        return True

    async def _check_reader(self) -> None:
        """Every :data:`READER_CHECK_S`: can this replica read other replicas' no_drop
        frames from the stream? While it cannot (its consumer died with a NATS node and
        JetStream cannot make a new one yet), say so on the control subject, every check:
        the other replicas then send their no_drop frames over core NATS too, starting
        with their last :data:`HISTORY_S` (docs/scaling.md, "A reader away")."""
        away = False
        while True:
            kvloops.raise_if_cancelled()  # a cancellation a NATS request swallowed
            await asyncio.sleep(READER_CHECK_S)  # a check pace, not a synchronization
            remote, nc = self._remote, self._nc
            if remote is None or nc is None:
                continue
            healthy = await remote.healthy(READER_CHECK_S)
            if not healthy:
                if not away:
                    self.counters["reader_away"] += 1
                    log.warning("replica %s: cannot read other replicas' no_drop frames "
                                "from the stream: asking them for core NATS copies",
                                self.config.name)
                with contextlib.suppress(NatsError):
                    await nc.publish(self.reader_away_subject, self.config.name.encode())
            elif away:
                log.info("replica %s: reading other replicas' no_drop frames from the "
                         "stream again", self.config.name)
            away = not healthy

    @property
    def remote_subjects(self) -> tuple[str, ...]:
        """The stream subjects this replica reads other replicas' frames on."""
        return self._remote.subjects if self._remote is not None else ()

    # -- metrics ---------------------------------------------------------------------------

    def metric_families(self) -> Iterable[MetricFamily]:
        counters = dict(self.counters)
        counters["delivered"] += sum(h.feed.delivered for h in self._held.values()
                                     if h.feed is not None)
        acks = self.acks
        counters.update(pongs_held=acks.held, pongs_coalesced=acks.coalesced,
                        pongs_unstored=acks.unstored)
        return [
            ("fleetctl_cluster_sessions_total", "counter",
             "Shared sessions: no_drop frames stored in the stream (duplicates, failures, "
             "refusals, not queued), session record writes and failures, deletes, "
             "sessions taken over by another replica, malformed entries, consumer start "
             "failures, frames delivered from the stream; other replicas' frames read "
             "(remote), reader hand-overs on interest changes (handoffs, handoff_late) "
             "and refused ones (follow_failures); local senders' pongs held until their "
             "no_drop frames were stored (pongs_held), and sent before that, after "
             "0.25 s (pongs_unstored) or replaced by a later one (pongs_coalesced); other "
             "replicas' no_drop frames held for a missing one (order_held), gaps given "
             "up after 3 s (order_skipped), frames delivered after their successors "
             "(order_late), bad Fleetctl-Order values (order_malformed).",
             "event",
             {k: float(v) for k, v in counters.items()}),
            ("fleetctl_cluster_sessions_held", "gauge",
             "Sessions whose connection is on this replica.", "",
             {"": float(sum(1 for h in self._held.values() if h.attached))}),
        ]


def _transient(result: BaseException | None) -> bool:
    """A store failure worth retrying: a timeout, NATS away, no stream leader (no
    responders, or JetStream's 503 while it elects one). A refusal (a frame past
    ``max_payload``, any other API error) is not retried."""
    if isinstance(result, ServiceUnavailableError):
        return True
    return (isinstance(result, (TimeoutError, NatsError))
            and not isinstance(result, (APIError, MaxPayloadError)))
