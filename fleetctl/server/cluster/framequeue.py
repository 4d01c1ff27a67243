"""Frames waiting for NATS: a bounded FIFO, and the topic -> subject memo.

Both of a replica's ways into NATS use them: the core publish queue
(:class:`~fleetctl.server.cluster.natsfanout.NatsFanout`) and the no_drop stream's store
queue (:class:`~fleetctl.server.cluster.sharedsessions.SharedSessions`). Every queue is
bounded in frames and bytes (``cluster.publish_queue_frames``/``_bytes``); the caller
counts what does not fit.
"""

from __future__ import annotations

import asyncio
import hashlib
from collections import OrderedDict, deque
from collections.abc import Callable, Iterator
from typing import NamedTuple

# Topics remembered with their subject (cleared, not evicted one by one, when full).
MAX_MEMO_TOPICS = 16384
# How many digests of other replicas' no_drop frames a replica remembers to drop a
# second copy (one came over core NATS, the other from the stream).
MAX_RECENT_DIGESTS = 16384


def frame_digest(frame: bytes) -> str:
    """A no_drop frame's identity between replicas (the stream's ``Nats-Msg-Id``): equal
    frames are the same frame (a robot's resend through another replica too)."""
    return hashlib.blake2b(frame, digest_size=16).hexdigest()


class RecentDigests:
    """The digests of the last :data:`MAX_RECENT_DIGESTS` frames delivered."""

    def __init__(self, size: int = MAX_RECENT_DIGESTS) -> None:
        self._size = size
        self._seen: OrderedDict[str, None] = OrderedDict()

    def first(self, digest: str) -> bool:
        """``True`` the first time *digest* is seen (remembered from then on)."""
        seen = self._seen
        if digest in seen:
            return False
        seen[digest] = None
        if len(seen) > self._size:
            seen.popitem(last=False)
        return True


class Queued(NamedTuple):
    """One frame waiting for NATS."""

    subject: str
    frame: bytes
    topic: str
    no_drop: bool
    message_id: int | None = None  # a fragment's message (local delivery groups by it)
    digest: str | None = None  # a no_drop frame's: receivers drop a second copy by it
    order: str | None = None  # a no_drop frame's Fleetctl-Order (remoteorder.py)


_tuple_new = tuple.__new__


def queued(subject: str, frame: bytes, topic: str, no_drop: bool,
           message_id: int | None = None, digest: str | None = None,
           order: str | None = None) -> Queued:
    """A :class:`Queued`, made at a third of the NamedTuple constructor's cost (0.15
    against 0.47 us here): one is made per frame published."""
    return _tuple_new(Queued, (subject, frame, topic, no_drop, message_id, digest, order))


class FrameQueue:
    """A FIFO of :class:`Queued` frames bounded in frames and bytes.

    Args:
        max_frames: At most this many frames.
        max_bytes: At most this many frame bytes.
        wake: Set when the queue becomes non-empty (its consumer task waits on it).
    """

    def __init__(self, max_frames: int, max_bytes: int, wake: asyncio.Event) -> None:
        self.max_frames = max_frames
        self.max_bytes = max_bytes
        self.wake = wake
        self._entries: deque[Queued] = deque()
        self.bytes = 0

    def put(self, entry: Queued) -> bool:
        """Append *entry*; ``False`` (not queued) past either bound."""
        entries = self._entries
        if (len(entries) >= self.max_frames
                or self.bytes + len(entry.frame) > self.max_bytes):
            return False
        entries.append(entry)
        self.bytes += len(entry.frame)
        if len(entries) == 1:
            self.wake.set()
        return True

    def popleft(self) -> Queued:
        entry = self._entries.popleft()
        self.bytes -= len(entry.frame)
        return entry

    def head(self, n: int) -> list[Queued]:
        """The first *n* entries (fewer if there are fewer), left in place."""
        entries = self._entries
        return [entries[i] for i in range(min(n, len(entries)))]

    def keep(self, wanted: Callable[[Queued], bool]) -> int:
        """Remove the entries *wanted* refuses, in place; return how many."""
        kept = [entry for entry in self._entries if wanted(entry)]
        removed = len(self._entries) - len(kept)
        if removed:
            self._entries = deque(kept)
            self.bytes = sum(len(entry.frame) for entry in kept)
        return removed

    def __len__(self) -> int:
        return len(self._entries)

    def __getitem__(self, index: int) -> Queued:
        """The entry at *index* (0: the oldest), left in place."""
        return self._entries[index]

    def __iter__(self) -> Iterator[Queued]:
        return iter(self._entries)


class SubjectMemo:
    """``topic -> subject`` for a subject mapping (:func:`~fleetctl.server.cluster.
    subjects.topic_subject` under some root), computed once per topic."""

    def __init__(self, root: str, mapping: Callable[[str, str], str]) -> None:
        self._root = root
        self._mapping = mapping
        self._memo: dict[str, str] = {}

    def __call__(self, topic: str) -> str:
        subject = self._memo.get(topic)
        if subject is None:
            subject = self._mapping(self._root, topic)
            if len(self._memo) >= MAX_MEMO_TOPICS:
                self._memo.clear()
            self._memo[topic] = subject
        return subject
