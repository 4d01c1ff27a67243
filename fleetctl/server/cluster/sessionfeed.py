"""One attached session's no_drop frames, read from the replicas' no_drop stream.

In a cluster a session's connection gets its no_drop frames from JetStream, not from the
live fan-out (docs/scaling.md, "Sessions"): an ordered consumer on the stream, starting
after the session's cursor, hands each frame the connection subscribed to and may receive
to its outbound scheduler. Frames of one stream come in stream order, so a session resumed
on any replica gets what it missed, in order, and then the live frames, with no seam.

The cursor follows the connection's acknowledgements: each frame queued here is
remembered with its stream sequence; when the outbound scheduler counts frames
acknowledged (a pong after them), their sequences retire and the last becomes the cursor.
A connection that dies leaves its cursor at the last acknowledged frame, so what was
in flight is replayed next time (the clients drop the duplicates by topic and sequence).

Back-pressure instead of drops: while the connection's no_drop FIFO is half full the
consumer's callback waits (JetStream's flow control then stops sending), so a session that
was away for long streams its backlog at the pace its connection takes it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Callable

from nats.aio.msg import Msg
from nats.js import JetStreamContext

from fleetctl.server.cluster.orderedconsumer import subscribe_ordered
from fleetctl.server.outbound import OutboundScheduler
from fleetctl.wire.errors import WireError
from fleetctl.wire.metadata import read_metadata

log = logging.getLogger("fleetctl.server.cluster")

# How often a callback waiting for room in the connection's queue looks again.
ROOM_LOOK_S = 0.01
# Frames NATS may hold for the consumer in this process (its flow control keeps it lower).
PENDING_MESSAGES = 4096
PENDING_BYTES = 32 * 1024 * 1024


class SessionFeed:
    """Feeds one connection its session's no_drop frames from the stream.

    Args:
        outbound: The connection's scheduler (ack tracking on).
        wants: Whether the connection subscribed to a topic and may receive it.
        is_open: Whether the connection is still open (a closed one gets nothing more).
        cursor: The session's cursor (start after it), or ``None``.
        since: Wall-clock start of the session (used while *cursor* is ``None``).
        on_malformed: Counts a stream message that is not a frame.
        bypass: Whether the stream is away (NATS lost, stores failing): the relay then
            queues local no_drop frames to the connection live (:meth:`note_live`), and
            the stream's copies come again later as duplicates the clients drop.
    """

    def __init__(self, outbound: OutboundScheduler, wants: Callable[[str], bool],
                 is_open: Callable[[], bool], cursor: int | None, since: float,
                 on_malformed: Callable[[], None],
                 bypass: Callable[[], bool] = lambda: False) -> None:
        self.bypass = bypass
        self._outbound = outbound
        self._wants = wants
        self._is_open = is_open
        self.cursor = cursor
        self._since = since
        self._on_malformed = on_malformed
        self._last_seq = cursor or 0
        # Without a cursor: messages stored before the session began are not its own.
        self._floor_s: float | None = since if cursor is None else None
        self._queued: deque[int] = deque()  # sequences queued, not yet acknowledged
        self._acked_seen = outbound.acked_total
        self._sub: JetStreamContext.PushSubscription | None = None
        self.subjects: tuple[str, ...] = ()  # the running consumer's filter
        self.delivered = 0

    async def start(self, js: JetStreamContext, stream: str, subjects: tuple[str, ...]) -> None:
        """Create the ordered consumer on *subjects* (the session's patterns as stream
        subjects): after the last frame this feed saw, else after the cursor, else from
        the session's start.

        Raises:
            nats.errors.Error: NATS or JetStream refused (the caller logs and retries).
        """
        # Before the first message, the time floor in _on_msg applies too.
        self._sub = await subscribe_ordered(
            js, stream, subjects, self._on_msg,
            start_seq=self._last_seq + 1 if self._last_seq else None, start_time=self._since,
            pending_msgs=PENDING_MESSAGES, pending_bytes=PENDING_BYTES)
        self.subjects = subjects

    async def stop(self) -> None:
        """Delete the consumer (the connection is gone or taken over, or its patterns
        changed: :meth:`start` then goes on after the last frame seen)."""
        sub, self._sub = self._sub, None
        self.subjects = ()
        if sub is not None:
            with contextlib.suppress(Exception):
                await sub.unsubscribe()

    @property
    def running(self) -> bool:
        return self._sub is not None

    def settle(self) -> int | None:
        """Move the cursor over every frame the connection acknowledged; return it."""
        acked = self._outbound.acked_total
        queued = self._queued
        while self._acked_seen < acked and queued:
            seq = queued.popleft()
            if seq >= 0:  # not a live frame (note_live)
                self.cursor = seq
            self._acked_seen += 1
        self._acked_seen = acked
        return self.cursor

    async def _on_msg(self, msg: Msg) -> None:
        seq = msg.metadata.sequence.stream
        if seq <= self._last_seq:
            return  # a re-created consumer may start at one we already have
        self._last_seq = seq
        if self._floor_s is not None:
            if msg.metadata.timestamp.timestamp() < self._floor_s:
                self._skip(seq)
                return
            self._floor_s = None
        try:
            topic = read_metadata(msg.data).topic
        except WireError:
            self._on_malformed()
            self._skip(seq)
            return
        if not self._wants(topic):
            self._skip(seq)
            return
        outbound = self._outbound
        limit = outbound.max_no_drop_messages // 2 or 1
        while outbound.no_drop_queued >= limit and self._is_open():
            await asyncio.sleep(ROOM_LOOK_S)  # back-pressure: NATS's flow control waits
        if not self._is_open():
            return
        if outbound.push(topic, msg.data, True):
            self._queued.append(seq)
            self.delivered += 1

    def note_live(self) -> None:
        """The relay queued a no_drop frame to the connection live (the stream is away):
        it takes a place in the acknowledgement order without moving the cursor."""
        self._queued.append(-1)

    def _skip(self, seq: int) -> None:
        """A frame not for this connection: once everything before it is acknowledged,
        the cursor may pass it (a later replay need not read it again)."""
        self.settle()
        if not self._queued:
            self.cursor = seq
