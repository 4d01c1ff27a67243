"""Which topics exist, with which ROS 2 type: the channels a Foxglove viewer is offered.

The relay core calls :meth:`TopicCatalog.note` for every accepted frame (hot path: one dict
lookup per frame once a topic is known) and :meth:`TopicCatalog.forget` when a connection
closes. A channel ``(topic, type)`` exists while at least one open connection has sent it,
and lingers ``linger_s`` after the last one closed: a robot that takes over its standby
connection or reconnects sends it again on its new connection, and its channel stays
(unadvertising it ended every viewer's subscription to it). Listeners (the Foxglove
adapter) hear when one appears or goes away, and each decides per viewer whether its
receive rules show it.

A fragmented or compressed frame does not say its message's type; for such a topic the
catalog reassembles and decodes the sender's frames until one message completes (a
:class:`~fleetctl.wire.ros2msg.FrameTranscoder` of its own, bounded), then stops looking.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Protocol

from fleetctl.server.foxglove.messages import Channel
from fleetctl.wire.codec import Codec
from fleetctl.wire.compression import COMPRESSED_TYPE
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import FRAGMENT_TYPE
from fleetctl.wire.ros2msg import FrameTranscoder, schema_text

log = logging.getLogger("fleetctl.server.foxglove")

# Why: topic names come from senders; a sender inventing topics must not grow this forever.
MAX_CHANNELS = 4096
MAX_TOPICS_PER_SENDER = 1024
# A topic whose type is still unknown after this many frames is given up on (not offered).
MAX_PROBE_FRAMES = 64
_UNKNOWN = ""
_GAVE_UP = "?"


class Sender(Protocol):
    """What the catalog needs of a connection (a :class:`~fleetctl.server.peer.Peer`)."""

    peer_id: int


Listener = Callable[[Channel, bool], None]
"""Called with ``(channel, added)`` when a channel appears (``True``) or goes (``False``)."""

CallLater = Callable[[float, Callable[[], None]], object]
"""Runs a callback after a delay in seconds (the event loop's ``call_later``)."""


def _loop_call_later(delay_s: float, callback: Callable[[], None]) -> object:
    return asyncio.get_running_loop().call_later(delay_s, callback)


class TopicCatalog:
    """Channels of the topics open connections send.

    Args:
        codec: Decodes frames (type probing); its registry gives the schemas.
        max_message_bytes: Largest reassembled or decompressed frame, bytes (probing).
        clock: Monotonic clock, seconds (reassembly timeouts while probing).
        linger_s: Seconds a channel stays after its last sender closed; 0: it goes at
            once.
        call_later: Runs the end of a linger (default: the running event loop's).
    """

    def __init__(self, codec: Codec, max_message_bytes: int,
                 clock: Callable[[], float] = time.monotonic, linger_s: float = 0.0,
                 call_later: CallLater = _loop_call_later) -> None:
        self.codec = codec
        self._clock = clock
        self.linger_s = linger_s  # read at each linger's start
        self._call_later = call_later
        # Channels without a sender, lingering: channel id -> the linger's number (a
        # channel sent again and left again starts a new linger; the old timer is void).
        self._lingering: dict[int, int] = {}
        self._lingers = 0
        self._probe = FrameTranscoder(codec, max_message_bytes)
        self._sent: dict[int, dict[str, str]] = {}  # peer id -> topic -> type ("" probing)
        self._probes: dict[tuple[int, str], int] = {}  # frames probed so far
        self._publishers: dict[int, set[int]] = {}  # channel id -> peer ids
        # (topic, type) -> channel id, kept after the channel ends so that a topic coming
        # back gets its id again; ids of ended channels are forgotten when the table is
        # full (_make_room), and an id is never given twice (_last_id).
        self._ids: dict[tuple[str, str], int] = {}
        self._last_id = 0
        self._channels: dict[int, Channel] = {}  # live channels
        self._schemas: dict[str, str | None] = {}
        self.listeners: list[Listener] = []
        self.refused = 0  # channels not offered: over a bound, or no schema

    def channels(self) -> list[Channel]:
        """Every live channel."""
        return list(self._channels.values())

    def channel(self, channel_id: int) -> Channel | None:
        """The live channel *channel_id*, or ``None``."""
        return self._channels.get(channel_id)

    def note(self, sender: Sender, topic: str, type_name: str, frame: bytes) -> None:
        """*sender* sent *frame* (of metadata type *type_name*) on *topic*; the relay
        accepted it. Never raises."""
        topics = self._sent.get(sender.peer_id)
        if topics is None:
            topics = self._sent[sender.peer_id] = {}
        known = topics.get(topic)
        if known is not None and known != _UNKNOWN:
            return
        if known is None and len(topics) >= MAX_TOPICS_PER_SENDER:
            return
        if type_name in (FRAGMENT_TYPE, COMPRESSED_TYPE):
            type_name = self._probe_type(sender.peer_id, topic, frame)
        topics[topic] = type_name
        if type_name not in (_UNKNOWN, _GAVE_UP):
            self._add(sender.peer_id, topic, type_name)

    def forget(self, sender: Sender) -> None:
        """*sender* closed: its channels go unless another connection sends them."""
        topics = self._sent.pop(sender.peer_id, None) or {}
        self._probe.forget(sender.peer_id)
        for topic, type_name in topics.items():
            self._probes.pop((sender.peer_id, topic), None)
            channel_id = self._ids.get((topic, type_name))
            publishers = self._publishers.get(channel_id) if channel_id is not None else None
            if channel_id is None or publishers is None:
                continue
            publishers.discard(sender.peer_id)
            if not publishers:
                del self._publishers[channel_id]
                self._linger(channel_id)

    def _linger(self, channel_id: int) -> None:
        """Keep the channel *channel_id*, now without a sender, for ``linger_s``."""
        if self.linger_s <= 0:
            self._end(channel_id)
            return
        self._lingers += 1
        number = self._lingering[channel_id] = self._lingers
        self._call_later(self.linger_s, lambda: self._linger_ended(channel_id, number))

    def _linger_ended(self, channel_id: int, number: int) -> None:
        if self._lingering.get(channel_id) == number:  # nobody sent it meanwhile
            del self._lingering[channel_id]
            self._end(channel_id)

    def _end(self, channel_id: int) -> None:
        self._tell(self._channels.pop(channel_id), added=False)

    def _probe_type(self, peer_id: int, topic: str, frame: bytes) -> str:
        key = (peer_id, topic)
        tries = self._probes.get(key, 0) + 1
        self._probes[key] = tries
        try:
            done = self._probe.feed(peer_id, frame, self._clock())
        except WireError:
            done = None
        if done is not None:
            del self._probes[key]
            return done.type
        if tries >= MAX_PROBE_FRAMES:
            del self._probes[key]
            return _GAVE_UP
        return _UNKNOWN

    def _add(self, peer_id: int, topic: str, type_name: str) -> None:
        key = (topic, type_name)
        channel_id = self._ids.get(key)
        if channel_id is None:
            if len(self._ids) >= MAX_CHANNELS and not self._make_room():
                self.refused += 1
                return
            self._last_id += 1
            channel_id = self._ids[key] = self._last_id
        publishers = self._publishers.get(channel_id)
        if publishers is not None:
            publishers.add(peer_id)
            return
        if self._lingering.pop(channel_id, None) is not None:  # sent again: it stays
            self._publishers[channel_id] = {peer_id}
            return
        schema = self._schema(type_name)
        if schema is None:
            self.refused += 1
            return
        self._publishers[channel_id] = {peer_id}
        channel = self._channels[channel_id] = Channel(channel_id, topic, type_name, schema)
        self._tell(channel, added=True)

    def _make_room(self) -> bool:
        """Forget the ids of channels that ended (no sender, not lingering); whether
        that made room. Why: the ids of every (topic, type) ever sent were kept, so on a
        relay whose robots come and go under new names (a week of sims, replays, renamed
        robots) the table filled and no new topic was ever offered to Foxglove again.
        One pass over the table when it is full: amortized over the ids it frees."""
        live = self._channels.keys() | self._lingering.keys()
        self._ids = {key: i for key, i in self._ids.items() if i in live}
        return len(self._ids) < MAX_CHANNELS

    def _schema(self, type_name: str) -> str | None:
        if type_name not in self._schemas:
            try:
                self._schemas[type_name] = schema_text(self.codec.registry, type_name)
            except WireError as exc:
                log.warning("no Foxglove channel for type %s: %s", type_name, exc)
                self._schemas[type_name] = None
        return self._schemas[type_name]

    def _tell(self, channel: Channel, *, added: bool) -> None:
        for listener in self.listeners:
            listener(channel, added)
