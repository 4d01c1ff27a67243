"""What a window of a recording needs from before it: the newest latched message and the
current video group of each channel before a time.

Why: a merged window (``fleetctl recordings merge --since``) is opened in Foxglove or
replayed alone, like a rotated file. A map, ``/tf_static`` or a robot description is
published once (latched) and a camera sent as ``CompressedVideo`` decodes only from a
keyframe, so a window that starts after them shows no map and no camera until the next
keyframe. The recorder's rotation solves this by starting each new file with copies
(:mod:`fleetctl.server.recording.writer`); :func:`before` finds what the merge copies to
the start of its window the same way:

- **Latched channels**: the rotation's rule, read back from what the recording stores: a
  channel whose rosbag2 ``offered_qos_profiles`` say ``transient_local``
  (:func:`fleetctl.server.recording.latched.is_latched`; the writer marks a frame's
  latched flag so). Only the newest message before the time, per channel.
- **Video channels** (schema ``foxglove_msgs/msg/CompressedVideo``): the frames from the
  last keyframe before the time up to it (the keyframe test of
  :mod:`fleetctl.server.recording.gop`). At most :data:`MAX_GROUP_BYTES` per channel are
  read back looking for the keyframe; a channel past it is not carried, and named.

Read through the index, newest first (the ``mcap`` reader's reverse order, filtered to
those channels' chunks), stopping when every channel has what it needs: the messages
before the time are not held, only what is carried.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, BinaryIO

from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Schema

from fleetctl.server.recording.gop import VIDEO_TYPE, GopKeeper
from fleetctl.server.recording.latched import is_latched

MAX_GROUP_BYTES = 64 * 1024 * 1024
"""Bytes of a video channel read back from the time looking for its last keyframe (a
2-second group at 8 Mbit/s is 2 MB): past it, the channel is not carried."""


@dataclass
class CarriedChannel:
    """What is carried of one channel of one input.

    Attributes:
        schema: The channel's schema (``None``: none).
        channel: The input's channel.
        messages: Oldest first: a latched channel's newest message, or a video channel's
            frames from its last keyframe.
    """

    schema: Schema | None
    channel: Channel
    messages: list[Message] = field(default_factory=list)

    @property
    def newest_ns(self) -> int:
        """Log time of the newest message carried."""
        return self.messages[-1].log_time


@dataclass
class Found:
    """What :func:`before` found in one input.

    Attributes:
        carried: By the input's channel id.
        not_carried: Topics of video channels whose last keyframe was not found within
            :data:`MAX_GROUP_BYTES` (or before the input's start).
    """

    carried: dict[int, CarriedChannel] = field(default_factory=dict)
    not_carried: set[str] = field(default_factory=set)


Deserialize = Callable[[bytes, str], Any]


def before(stream: BinaryIO, time_ns: int, wants: Callable[[str], bool],
           deserialize: Callable[[], Deserialize]) -> Found:
    """The newest latched message and the current video group of each selected channel
    of the indexed MCAP file *stream*, before *time_ns*.

    Args:
        stream: The file, open for reading (it has a summary with chunk indexes).
        time_ns: The window's start: log times before it are searched.
        wants: Whether a topic is selected.
        deserialize: Gives ``deserialize(cdr, type_name)`` for the keyframe test (called
            only when the file has a video channel).

    Raises:
        McapError, zstandard.ZstdError, ...: The file is damaged (the caller names it).
    """
    reader = SeekingReader(stream, validate_crcs=True)
    summary = reader.get_summary()
    if summary is None:
        return Found()
    selected = [c for c in summary.channels.values() if wants(c.topic)]
    latched = {c.id for c in selected if is_latched(c.metadata)}
    videos = {c.id for c in selected if c.id not in latched
              and _schema_name(summary.schemas, c) == VIDEO_TYPE}
    if not latched and not videos:
        return Found()
    search = _Search(latched, videos, GopKeeper(0, deserialize()).keyframe if videos
                     else None)
    topics = sorted({summary.channels[i].topic for i in latched | videos})
    for schema, channel, message in reader.iter_messages(topics=topics, reverse=True,
                                                         ending_before=time_ns):
        if search.take(schema, channel, message):
            break
    return search.result()


class _Search:
    """The messages read newest first, kept while their channel needs more."""

    def __init__(self, latched: set[int], videos: set[int],
                 keyframe: Callable[[str, bytes], bool | None] | None) -> None:
        self._latched = latched
        self._videos = videos
        self._keyframe = keyframe
        self._pending = latched | videos
        self._keyed: set[int] = set()
        self._read_bytes: dict[int, int] = {}
        self._found = Found()

    def take(self, schema: Schema | None, channel: Channel, message: Message) -> bool:
        """Keep *message* if its channel needs it; whether every channel has what it
        needs (the search is over)."""
        if channel.id not in self._pending:  # a topic's other channel, or one done
            return False
        found = self._found.carried.setdefault(channel.id, CarriedChannel(schema, channel))
        found.messages.append(message)  # newest first until result()
        if channel.id in self._latched:
            self._pending.discard(channel.id)
        elif self._keyframe is not None and self._keyframe(VIDEO_TYPE, message.data):
            self._keyed.add(channel.id)
            self._pending.discard(channel.id)
        else:
            read = self._read_bytes.get(channel.id, 0) + len(message.data)
            self._read_bytes[channel.id] = read
            if read > MAX_GROUP_BYTES:  # given up: not held to the end
                self._give_up(channel.id)
        return not self._pending

    def result(self) -> Found:
        """What was found, each channel's messages oldest first."""
        for channel_id in self._videos - self._keyed:  # no keyframe before the start
            self._give_up(channel_id)
        for found in self._found.carried.values():
            found.messages.reverse()
        return self._found

    def _give_up(self, channel_id: int) -> None:
        self._pending.discard(channel_id)
        given_up = self._found.carried.pop(channel_id, None)
        if given_up is not None:
            self._found.not_carried.add(given_up.channel.topic)


def _schema_name(schemas: dict[int, Schema], channel: Channel) -> str:
    schema = schemas.get(channel.schema_id)
    return schema.name if schema is not None else ""
