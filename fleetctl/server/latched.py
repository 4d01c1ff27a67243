"""The latched store: the last complete latched message per (sender, topic).

A frame whose metadata says ``latched`` (docs/wire.md) comes from a ROS publisher with
``TRANSIENT_LOCAL`` durability: a map, ``/tf_static``, a robot description, published once.
The relay routes it like any frame and also hands it to :class:`LatchedStore`, which keeps
the newest complete message of each (sender identity set, topic), so a subscriber that
comes later gets it first (:meth:`fleetctl.server.relay.RelayCore` queues it with
:meth:`~fleetctl.server.outbound.OutboundScheduler.push_latched`).

What is kept is what came on the wire, frame for frame: a whole frame, a Compressed frame
(as is), or the fragment frames of one message. Fragments are kept as they arrive, per
(sender, topic) for one message at a time (a newer ``message_id`` replaces an incomplete
one); once every index of ``count`` arrived, the fragment list becomes the stored message
and replaces the previous one. The server never reassembles: it neither decodes the
payload nor checks it (receivers do, as for live fragments). Trade-off: a receiver that
already reassembled that ``message_id`` may take the repeat as stale (fleetctl's Python
``Reassembler`` does; it delivered the message already), the web page takes it again.

Bounds (``docs/server.md``): every byte counted is a frame byte (fragment overhead
included), incomplete messages too. A message over ``max_message_bytes`` (its declared
``total_bytes`` or its frames) is not kept, and the sender's older message on that topic
is forgotten with it, so the store never serves a message older than the sender's newest.
Past ``max_bytes`` (or ``max_entries`` keys), the least recently updated entries are
evicted. Each of these is counted in :attr:`Metrics.latched_events`; a message refused as
too big is also one WARNING per (sender, topic) naming the topic, its size and the
setting, since a late viewer then gets no map and the count alone says nowhere which.

The store lives in memory: a restarted single-process server has none until the senders
publish again (a fleetctl robot client republishes what its ``TRANSIENT_LOCAL``
subscriptions hold when it reconnects, as any late-joining ROS subscriber would get it).
Relay replicas share it (:mod:`fleetctl.server.cluster.sharedlatched`): the store tells its
:attr:`LatchedStore.listener` what local senders stored or lost, and takes the other
replicas' messages with :meth:`LatchedStore.put_remote` / :meth:`LatchedStore.forget_remote`.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from fleetctl.server.metrics import Metrics
from fleetctl.server.regex import FullMatch
from fleetctl.server.topicindex import TopicIndex
from fleetctl.wire.fragments import FragmentHeader

log = logging.getLogger("fleetctl.server.latched")

SenderKey = tuple[str, ...]
"""The sending connection's identity names, sorted (a robot's address identity, a person's
token identity): who the message is kept for, and what an auth reload re-checks."""

# Why: keys come from senders' topics; a sender inventing latched topics must not grow the
# index past this even with tiny messages.
MAX_ENTRIES = 4096


class LatchedListener(Protocol):
    """Hears what local senders' messages did in the store (replicas share them)."""

    def stored(self, sender: SenderKey, topic: str, frames: list[bytes]) -> None:
        """A local sender's complete message is now the one kept for (sender, topic)."""

    def forgotten(self, sender: SenderKey, topic: str) -> None:
        """Nothing may be served for (sender, topic) any more: its newest message was too
        big to keep, or an auth reload revoked the sender."""


@dataclass
class _Message:
    """Frames of one latched message, in order (one whole frame, or fragments by index)."""

    message_id: int | None  # None: a whole frame, or a message from another replica
    frames: list[bytes]
    nbytes: int
    remote: bool = False  # came from another replica (put_remote)


@dataclass
class _Pending:
    """Fragments of a latched message still arriving."""

    message_id: int
    count: int
    total_bytes: int
    parts: dict[int, bytes] = field(default_factory=dict)
    nbytes: int = 0


@dataclass
class _Entry:
    stored: _Message | None = None
    pending: _Pending | None = None
    refused_id: int | None = None  # a fragmented message too big to keep: skip the rest

    @property
    def nbytes(self) -> int:
        return ((self.stored.nbytes if self.stored else 0)
                + (self.pending.nbytes if self.pending else 0))


class LatchedStore:
    """Bounded store of the newest latched message per (sender, topic).

    Args:
        max_bytes: Bytes kept in total (stored and incomplete messages).
        max_message_bytes: Largest message kept, bytes.
        metrics: Counters to update (``latched_events``) and the two gauges it sets
            (``latched_bytes``, ``latched_messages``).
        max_entries: (sender, topic) keys kept.
    """

    def __init__(self, max_bytes: int, max_message_bytes: int, metrics: Metrics,
                 max_entries: int = MAX_ENTRIES) -> None:
        self.max_bytes = max_bytes
        self.max_message_bytes = min(max_message_bytes, max_bytes)
        self.max_entries = max_entries
        self._metrics = metrics
        self._entries: OrderedDict[tuple[SenderKey, str], _Entry] = OrderedDict()
        self._nbytes = 0
        # Topic -> senders with a stored message on it (the index of messages()).
        self._topics: dict[str, dict[SenderKey, None]] = {}
        # The same topics, in the same order, sorted too: what a new subscription is
        # matched against (candidates()).
        self._index = TopicIndex()
        self._stored = 0
        self.listener: LatchedListener | None = None
        # (sender, topic) keys a too-big message was said for, oldest first; bounded like
        # the entries (a forgotten one may be said again).
        self._warned: OrderedDict[tuple[SenderKey, str], None] = OrderedDict()
        self._setting = ("limits.latched_message_bytes" if max_message_bytes <= max_bytes
                         else "limits.latched_bytes")

    @property
    def nbytes(self) -> int:
        """Bytes held now (stored and incomplete messages)."""
        return self._nbytes

    def __len__(self) -> int:
        """Complete messages held now."""
        return self._stored

    def topics(self) -> list[str]:
        """Topics with at least one stored message."""
        return list(self._topics)

    def candidates(self, patterns: Sequence[FullMatch]) -> list[str]:
        """Topics with a stored message that one of *patterns* may match (a superset of
        those they match; see :meth:`TopicIndex.candidates`), in :meth:`topics` order."""
        return self._index.candidates(patterns)

    def messages(self, topic: str) -> list[list[bytes]]:
        """The stored messages of *topic* (one per sender, in the order they were first
        stored), each as the list of frames to send in order."""
        out = []
        for sender in self._topics.get(topic, ()):
            stored = self._entries[(sender, topic)].stored
            assert stored is not None
            out.append(stored.frames)
        return out

    def local_messages(self) -> list[tuple[SenderKey, str, list[bytes]]]:
        """``(sender, topic, frames)`` of every stored message a sender sent to this relay
        (not those shared by other replicas), oldest update first."""
        return [(sender, topic, entry.stored.frames)
                for (sender, topic), entry in self._entries.items()
                if entry.stored is not None and not entry.stored.remote]

    def put(self, sender: SenderKey, topic: str, frame: bytes,
            fragment: FragmentHeader | None) -> None:
        """Take one latched frame the relay accepted from *sender*.

        Args:
            sender: The sender's identity names, sorted.
            topic: The frame's topic.
            frame: The frame as received (kept by reference).
            fragment: Its Fragment header when it is a fragment, else ``None``.
        """
        key = (sender, topic)
        entry = self._touch(key)
        before = entry.nbytes
        if fragment is None:
            self._put_whole(entry, key, frame)
        else:
            self._put_fragment(entry, key, frame, fragment)
        self._nbytes += entry.nbytes - before
        if entry.stored is None and entry.pending is None and entry.refused_id is None:
            del self._entries[key]  # (a refusal is remembered: the rest of its fragments)
        self._enforce_bounds(key)

    def _touch(self, key: tuple[SenderKey, str]) -> _Entry:
        """The entry of *key*, made if new, now the most recently updated."""
        entry = self._entries.get(key)
        if entry is None:
            entry = self._entries[key] = _Entry()
        else:
            self._entries.move_to_end(key)
        return entry

    def _put_whole(self, entry: _Entry, key: tuple[SenderKey, str], frame: bytes) -> None:
        entry.refused_id = None
        if entry.pending is not None:  # an older message, never completed
            entry.pending = None
            self._count("superseded")
        if len(frame) > self.max_message_bytes:
            self._refuse(entry, key, len(frame))
            return
        self._store(entry, key, _Message(None, [frame], len(frame)))

    def _put_fragment(self, entry: _Entry, key: tuple[SenderKey, str], frame: bytes,
                      header: FragmentHeader) -> None:
        mid = header.message_id
        if mid == entry.refused_id or (entry.stored is not None
                                       and entry.stored.message_id == mid):
            return  # the rest of a message too big to keep, or a resend of the stored one
        pending = entry.pending
        if pending is not None and pending.message_id != mid:
            entry.pending = pending = None
            self._count("superseded")
        if pending is None:
            if header.total_bytes > self.max_message_bytes:
                entry.refused_id = mid
                self._refuse(entry, key, header.total_bytes)
                return
            pending = entry.pending = _Pending(mid, header.count, header.total_bytes)
        if (header.count != pending.count or header.total_bytes != pending.total_bytes
                or not header.index < header.count):
            entry.pending = None  # contradicting fragments: receivers will refuse it too
            self._count("malformed")
            return
        if header.index in pending.parts:
            return  # a duplicate (a resend after a reconnect)
        pending.parts[header.index] = frame
        pending.nbytes += len(frame)
        if pending.nbytes > self.max_message_bytes:
            entry.pending, entry.refused_id = None, mid
            self._refuse(entry, key, pending.nbytes)
        elif len(pending.parts) == pending.count:
            entry.pending = None
            frames = [pending.parts[i] for i in range(pending.count)]
            self._store(entry, key, _Message(mid, frames, pending.nbytes))

    def _store(self, entry: _Entry, key: tuple[SenderKey, str], message: _Message) -> None:
        if entry.stored is None:
            sender, topic = key
            senders = self._topics.get(topic)
            if senders is None:
                senders = self._topics[topic] = {}
                self._index.add(topic)
            senders[sender] = None
            self._stored += 1
        entry.stored = message
        if message.remote:
            self._count("remote_stored")
        else:
            self._count("stored")
            if self.listener is not None:
                self.listener.stored(key[0], key[1], message.frames)

    def _refuse(self, entry: _Entry, key: tuple[SenderKey, str], nbytes: int) -> None:
        """A message of *nbytes* too big to keep: forget the older one too (never serve
        stale)."""
        self._count("refused_too_big")
        self._warn_too_big(key, nbytes)
        self._unstore(entry, key)
        if self.listener is not None:
            self.listener.forgotten(*key)

    def _warn_too_big(self, key: tuple[SenderKey, str], nbytes: int) -> None:
        if key in self._warned:
            return
        if len(self._warned) >= self.max_entries:
            self._warned.popitem(last=False)
        self._warned[key] = None
        sender, topic = key
        log.warning("latched message on %s from %s not kept: %d bytes, over %s (%d): it is "
                    "relayed, but a subscriber that comes later does not get it (counted "
                    "in fleetctl_latched_events_total{event=\"refused_too_big\"}; said once "
                    "per sender and topic)", topic, ",".join(sender) or "?", nbytes,
                    self._setting, self.max_message_bytes)

    def _unstore(self, entry: _Entry, key: tuple[SenderKey, str]) -> None:
        if entry.stored is None:
            return
        entry.stored = None
        self._stored -= 1
        sender, topic = key
        senders = self._topics[topic]
        del senders[sender]
        if not senders:
            del self._topics[topic]
            self._index.discard(topic)

    def _enforce_bounds(self, keep: tuple[SenderKey, str]) -> None:
        """Evict least recently updated entries; *keep* (just updated, so the most
        recent) goes last, only if it alone is over the bound."""
        while self._nbytes > self.max_bytes or len(self._entries) > self.max_entries:
            key = next(iter(self._entries))
            self._drop(key)
            self._count("evicted")
            if key == keep:
                break
        self._gauges()

    def _gauges(self) -> None:
        self._metrics.latched_bytes = self._nbytes
        self._metrics.latched_messages = self._stored

    def _drop(self, key: tuple[SenderKey, str]) -> None:
        entry = self._entries.pop(key)
        self._nbytes -= entry.nbytes
        self._unstore(entry, key)

    def put_remote(self, sender: SenderKey, topic: str, frames: list[bytes]) -> bool:
        """Keep another replica's complete message for (*sender*, *topic*) as if it had
        been sent here (the listener is not told: it came from the shared store).

        Returns:
            Whether it is kept (not when over ``max_message_bytes``).
        """
        nbytes = sum(len(f) for f in frames)
        if not frames or nbytes > self.max_message_bytes:
            self._count("refused_too_big")
            return False
        key = (sender, topic)
        entry = self._touch(key)
        before = entry.nbytes
        self._store(entry, key, _Message(None, list(frames), nbytes, remote=True))
        self._nbytes += entry.nbytes - before
        self._enforce_bounds(key)
        return key in self._entries and entry.stored is not None

    def forget_remote(self, sender: SenderKey, topic: str) -> bool:
        """Another replica forgot (*sender*, *topic*): drop the message it had shared (a
        message a local sender stored since stays).

        Returns:
            Whether a message was dropped.
        """
        key = (sender, topic)
        entry = self._entries.get(key)
        if entry is None or entry.stored is None or not entry.stored.remote:
            return False
        before = entry.nbytes
        self._unstore(entry, key)
        self._nbytes += entry.nbytes - before
        if entry.pending is None and entry.refused_id is None:
            del self._entries[key]
        self._count("remote_forgotten")
        self._gauges()
        return True

    def drop_where(self, revoked: Callable[[SenderKey, str], bool]) -> int:
        """Drop every entry whose (sender, topic) *revoked* answers true for (an auth
        reload removed the sender's identity or its send permission on the topic).

        Returns:
            Entries dropped (each counted as ``revoked``).
        """
        keys = [k for k in self._entries if revoked(*k)]
        for key in keys:
            self._drop(key)
            self._count("revoked")
            if self.listener is not None:
                self.listener.forgotten(*key)
        self._gauges()
        return len(keys)

    def _count(self, event: str) -> None:
        events = self._metrics.latched_events
        events[event] = events.get(event, 0) + 1
