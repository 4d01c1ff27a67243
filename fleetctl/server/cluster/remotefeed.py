"""Other replicas' no_drop frames, read from the no_drop stream for this replica's
connections without a session, narrowed to what they subscribed to (issue 15).

No_drop frames cross replicas through the sessions' stream, not core NATS
(:mod:`~fleetctl.server.cluster.sharedsessions`). A replica reads only the stream subjects
its local interest covers (the same subjects it holds on core NATS, under the stream's
root): with no local subscriber it reads nothing, so no replica receives every no_drop
frame when nobody asked.

When the interest changes the one ordered consumer is replaced by one on the new subjects,
with nothing lost and nothing twice on a subject both follow:

1. read the stream's last sequence ``L``;
2. wait until the old consumer has handed over every frame of its subjects up to ``L``
   (JetStream says none is pending, and the last one it sent has been handled here);
3. start the new one after ``L`` while the old one still runs (the frames past ``L`` they
   both bring are the same frames: the digest check every remote frame passes drops the
   second copy), then stop the old one.

A subject just added so starts at ``L``: a new subscriber gets frames stored after its
subscription, not the stream's history. If the old consumer does not catch up within
:data:`HANDOFF_S` (a busy replica), the new one starts after the last frame the old one
handled instead, and skips the frames up to ``L`` on subjects the old one did not follow:
exact, at the cost of reading them again. Counted ``handoff_late``.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable, Iterable

from nats.aio.msg import Msg
from nats.errors import Error as NatsError
from nats.js import JetStreamContext

from fleetctl.server.cluster import kvloops
from fleetctl.server.cluster.orderedconsumer import subscribe_ordered
from fleetctl.server.cluster.remoteorder import ORDER_HEADER, order_subject
from fleetctl.server.cluster.subjects import (
    SUB_PENDING_BYTES,
    SUB_PENDING_MESSAGES,
    subject_matches,
)

# More subjects than this in the filter: read the stream's whole root instead (JetStream
# checks every filter subject per stored message).
MAX_FILTER_SUBJECTS = 256
# How long the old consumer may take to hand over what it was sent before a change.
HANDOFF_S = 2.0
HANDOFF_LOOK_S = 0.005


class _Reader:
    """One consumer and the last stream sequence it handled."""

    def __init__(self, subjects: tuple[str, ...], start_after: int) -> None:
        self.subjects = subjects
        self.last = start_after
        self.sub: JetStreamContext.PushSubscription | None = None


class RemoteFeed:
    """Reads the other replicas' no_drop frames on the subjects local interest covers.

    Args:
        stream: The no_drop stream's name.
        prefix: The live subjects' prefix (``cluster.subject_prefix``).
        root: The stream subjects' first token (``<prefix>_nd``).
        replica: This replica's name (its own frames are skipped: it delivered them
            locally when it accepted them).
        replica_header: The header naming the replica that stored a frame.
        on_frame: Takes every frame read: its ``Fleetctl-Order`` header, its subject after
            the root, the frame, whether it is the first copy here
            (``ReceiverOrder.offer_stream``: delivers a first copy to this replica's
            connections in its sender's order, and a second one vouches for the frames
            held before it).
        counters: Where ``remote``, ``handoffs`` and ``handoff_late`` are counted.
        first_copy: Whether a frame (by its digest) is new here: it may have come over
            core NATS already while this reader was away, or from both consumers while
            one replaces the other.
    """

    def __init__(self, stream: str, prefix: str, root: str, replica: str, replica_header: str,
                 on_frame: Callable[[str | None, str, bytes, bool], None],
                 counters: dict[str, int],
                 first_copy: Callable[[str | None], bool]) -> None:
        self._stream = stream
        self._prefix = prefix
        self._root = root
        self._replica = replica
        self._header = replica_header
        self._on_frame = on_frame
        self._first_copy = first_copy
        self._asked: tuple[str, ...] = ()  # what the last follow() asked for
        self.counters = counters
        for name in ("remote", "handoffs", "handoff_late"):
            counters.setdefault(name, 0)
        self._reader: _Reader | None = None
        # The consumer being started while the old one still runs: both deliver.
        self._incoming: _Reader | None = None
        # After a late handover: (L, the old subjects): frames up to L on other subjects
        # were stored before the change and are skipped.
        self._skip_unless: tuple[int, tuple[str, ...]] | None = None
        self._lock = asyncio.Lock()

    @property
    def subjects(self) -> tuple[str, ...]:
        """The stream subjects being read (empty: none)."""
        return self._reader.subjects if self._reader is not None else ()

    def stream_subjects(self, wanted: Iterable[str]) -> tuple[str, ...]:
        """The stream subjects of the live subjects *wanted* (already a cover: no two
        overlap), or the whole root past :data:`MAX_FILTER_SUBJECTS`."""
        cut = len(self._prefix)
        subjects = sorted(self._root + s[cut:] for s in wanted
                          if s.startswith(self._prefix + "."))
        if len(subjects) > MAX_FILTER_SUBJECTS:
            return (f"{self._root}.>",)
        return tuple(subjects)

    async def follow(self, js: JetStreamContext, wanted: Iterable[str]) -> None:
        """Read the subjects of *wanted* (the live subjects of local interest) from now on.

        Raises:
            nats.errors.Error, TimeoutError: NATS or JetStream refused; the caller retries
                (the old consumer, if any, still runs).
        """
        subjects = self._asked = self.stream_subjects(wanted)
        async with self._lock:
            old = self._reader
            if subjects == self.subjects:
                return
            if not subjects:  # nothing to hand over to
                self._reader = None
                if old is not None:
                    await _unsubscribe(old)
                return
            # The stream's answer may lag what a consumer already delivered here.
            last = max((await js.stream_info(self._stream)).state.last_seq,
                       old.last if old is not None else 0)
            start_after = last
            self._skip_unless = None
            if old is not None and not await self._handed_over(old, last):
                self.counters["handoff_late"] += 1
                start_after = min(old.last, last)
                self._skip_unless = (last, old.subjects)  # the old subjects pass it
            new = self._incoming = _Reader(subjects, start_after)
            try:
                new.sub = await subscribe_ordered(
                    js, self._stream, subjects, self._receiver(new),
                    start_seq=start_after + 1, pending_msgs=SUB_PENDING_MESSAGES,
                    pending_bytes=SUB_PENDING_BYTES)
                self._reader = new
            finally:
                self._incoming = None
            if old is not None:
                await _unsubscribe(old)
                self.counters["handoffs"] += 1

    async def healthy(self, timeout_s: float) -> bool:
        """Whether this replica reads what it asked for: nothing asked, or its consumer
        runs on those subjects and JetStream answers for it within *timeout_s* (a consumer
        whose NATS node died is re-created by nats-py only once JetStream can)."""
        if not self._asked:
            return True
        reader = self._reader
        sub = reader.sub if reader is not None else None
        if reader is None or sub is None or reader.subjects != self._asked:
            return False
        try:
            await asyncio.wait_for(sub.consumer_info(), timeout_s)
        except (TimeoutError, NatsError):
            kvloops.raise_if_cancelled()
            return False
        return True

    async def stop(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None:
            await _unsubscribe(reader)

    async def _handed_over(self, reader: _Reader, last: int) -> bool:
        """Wait until *reader* has handled every frame of its subjects up to *last*;
        ``False`` if it did not within :data:`HANDOFF_S`."""
        sub = reader.sub
        if sub is None:
            return True
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(HANDOFF_S):
                while True:
                    info = await sub.consumer_info()
                    sent = (info.delivered.stream_seq or 0) if info.delivered is not None else 0
                    if info.num_pending == 0 or sent >= last:
                        while reader.last < sent:  # its callback is catching up
                            await asyncio.sleep(HANDOFF_LOOK_S)
                        return True
                    await asyncio.sleep(HANDOFF_LOOK_S)  # a look pace, bounded above
        return False

    def _receiver(self, reader: _Reader) -> Callable[[Msg], Awaitable[None]]:
        async def receive(msg: Msg) -> None:
            seq = msg.metadata.sequence.stream
            if seq <= reader.last:
                return  # a re-created consumer may start at one already handled
            reader.last = seq
            if reader is not self._reader and reader is not self._incoming:
                return  # a replaced consumer's last frames: the new one has them
            skip = self._skip_unless
            if skip is not None and seq <= skip[0] and not any(
                    subject_matches(msg.subject, s) for s in skip[1]):
                return  # stored before the change, on a subject nobody here followed
            headers = msg.headers or {}
            if headers.get(self._header) == self._replica:
                return  # our own: delivered locally when it was accepted
            # A second copy (core NATS, or the other consumer of a replacement, brought
            # it) is not delivered, but still tells the order stage how far the stream is.
            first = self._first_copy(headers.get("Nats-Msg-Id"))
            if first:
                self.counters["remote"] += 1
            self._on_frame(headers.get(ORDER_HEADER), order_subject(msg.subject), msg.data,
                           first)

        return receive


async def _unsubscribe(reader: _Reader) -> None:
    sub, reader.sub = reader.sub, None
    if sub is not None:
        with contextlib.suppress(Exception):
            await sub.unsubscribe()
