"""Each video topic's frames since its last keyframe, for the start of the next file.

A recording file that starts between two keyframes of a camera sent as
``foxglove_msgs/msg/CompressedVideo`` cannot show that camera until the next keyframe
(2 s at fleet.yaml's default interval): every frame before it needs the ones before the
file. The writer (:mod:`fleetctl.server.recording.writer`) keeps the current group of
pictures of each video topic here, and a new file starts with it, as it starts with the
latched topics, so that a file opened or replayed alone shows the video from its first
moment. The copies repeat at most one group per topic and rotation.

Bounded: at most :data:`MAX_VIDEO_TOPICS` topics and *max_bytes* together (the writer
gives a quarter of ``max_file_bytes``); a group that outgrows its share is dropped until
the topic's next keyframe (that file then starts as before, at the next keyframe).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

from fleetctl.client.videobits import is_keyframe

log = logging.getLogger("fleetctl.server.recording")

VIDEO_TYPE = "foxglove_msgs/msg/CompressedVideo"
MAX_VIDEO_TOPICS = 64


class GopFrame(NamedTuple):
    """One kept video frame as it was recorded."""

    cdr: bytes
    publish_ns: int
    seq: int


class GopKeeper:
    """The frames of each video topic from its last keyframe on.

    Args:
        max_bytes: CDR bytes kept over all topics.
        deserialize: ``deserialize(cdr, type_name)`` of the recording's type store (the
            keyframe test needs the message's ``format`` and ``data``).
    """

    def __init__(self, max_bytes: int, deserialize: Callable[[bytes, str], Any]) -> None:
        self.max_bytes = max_bytes
        self._deserialize = deserialize
        self._gops: dict[str, list[GopFrame]] = {}
        self._bytes: dict[str, int] = {}
        self._warned: set[str] = set()

    def keyframe(self, type_name: str, cdr: bytes) -> bool | None:
        """Whether a message of *type_name* is a video keyframe; ``None``: not video (or
        unreadable, which the writer counts elsewhere)."""
        if type_name != VIDEO_TYPE:
            return None
        try:
            msg = self._deserialize(cdr, type_name)
            return is_keyframe(str(msg.format), memoryview(msg.data).cast("B"))
        except (ValueError, TypeError, IndexError, KeyError, AttributeError):
            return None

    def add(self, topic: str, frame: GopFrame, keyframe: bool) -> None:
        """Keep *frame* of *topic* (a keyframe starts a new group; a delta frame joins the
        group it follows, or nothing when no keyframe was kept)."""
        if keyframe:
            if topic not in self._gops and len(self._gops) >= MAX_VIDEO_TOPICS:
                self._warn(topic, f"more than {MAX_VIDEO_TOPICS} video topics")
                return
            self._gops[topic], self._bytes[topic] = [frame], len(frame.cdr)
        elif topic in self._gops:
            self._gops[topic].append(frame)
            self._bytes[topic] += len(frame.cdr)
        else:
            return
        if sum(self._bytes.values()) > self.max_bytes:
            self.forget(topic)
            self._warn(topic, f"its frames since the last keyframe passed {self.max_bytes} "
                       "bytes with the other video topics'")

    def forget(self, topic: str) -> None:
        """Drop *topic*'s group (kept again from its next keyframe)."""
        self._gops.pop(topic, None)
        self._bytes.pop(topic, None)

    def groups(self, skip: str | None = None) -> Iterator[tuple[str, GopFrame]]:
        """``(topic, frame)`` of every kept group but *skip*'s, each in order."""
        for topic, frames in self._gops.items():
            if topic != skip:
                for frame in frames:
                    yield topic, frame

    def _warn(self, topic: str, why: str) -> None:
        if topic not in self._warned and len(self._warned) < MAX_VIDEO_TOPICS:
            self._warned.add(topic)
            log.warning("recording: video %s does not start new files decodable: %s "
                        "(they start at its next keyframe)", topic, why)
