"""Keyframe request routing: who publishes each video topic, and how often to ask it.

A viewer that cannot decode a video topic (it joined between keyframes, or lost a frame a
later one depends on) sends ``fleetctl_msgs/msg/KeyframeRequest {string topic}`` on the
control topic ``/keyframe_requests`` (docs/wire.md). The relay forwards it, as is, to the
connection that most recently published a ``foxglove_msgs/msg/CompressedVideo`` frame on
that topic; the publisher needs no subscription for it. Requests are forwarded at most
once per topic per ``interval_s``: many viewers losing the same frame cost the robot one
keyframe, not one each (and a hostile viewer cannot make it send only keyframes).

Publishers are learnt from whole ``CompressedVideo`` frames only. A fragmented or
Compressed video frame names its wrapper's type, and the server never reassembles; delta
frames are small and whole, so a publisher is known from its first delta frame on.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Generic, TypeVar

from fleetctl.server.metrics import Metrics
from fleetctl.server.regex import FullMatch
from fleetctl.server.topicindex import TopicIndex
from fleetctl.wire.control import encode_keyframe_request

VIDEO_TYPE = "foxglove_msgs/msg/CompressedVideo"

# Why: topics are sender-chosen; a sender inventing video topics forgets the oldest.
MAX_VIDEO_TOPICS = 4096

C = TypeVar("C")


class KeyframeRouter(Generic[C]):
    """The last publisher of each video topic and the per-topic forward rate limit.

    Args:
        interval_s: Smallest time between two forwards on one topic, seconds.
        clock: Monotonic clock, seconds.
        metrics: Where outcomes are counted (``keyframe_requests``).
        max_topics: Video topics remembered (the least recently published is forgotten).
    """

    def __init__(self, interval_s: float, clock: Callable[[], float], metrics: Metrics,
                 max_topics: int = MAX_VIDEO_TOPICS) -> None:
        self.interval_s = interval_s
        self.max_topics = max_topics
        self._clock = clock
        self._metrics = metrics
        self._publisher: dict[str, C] = {}  # insertion order: oldest first
        self._index = TopicIndex()  # the same topics in the same order, sorted too
        self._last_forward_s: dict[str, float] = {}
        # The request the server itself sends for a topic (request_frame), encoded once:
        # a new ".*" subscription beside 4,096 video topics spent 100 ms encoding them.
        self._requests: dict[str, bytes] = {}

    def note_publisher(self, topic: str, conn: C) -> None:
        """*conn* just published a video frame on *topic* (the relay's hot path)."""
        if self._publisher.get(topic) is conn:
            return
        self._publisher.pop(topic, None)
        self._publisher[topic] = conn
        self._index.add(topic)  # (moved last, as in _publisher)
        if len(self._publisher) > self.max_topics:
            self._drop(next(iter(self._publisher)))

    def _drop(self, topic: str) -> None:
        del self._publisher[topic]
        self._index.discard(topic)
        self._last_forward_s.pop(topic, None)
        self._requests.pop(topic, None)

    def forget(self, conn: C) -> None:
        """A connection closed: it publishes nothing any more."""
        for topic in [t for t, c in self._publisher.items() if c is conn]:
            self._drop(topic)

    def publisher(self, topic: str) -> C | None:
        """The connection that last published *topic* as video, or ``None``."""
        return self._publisher.get(topic)

    def video_topics(self) -> list[str]:
        """Topics with a known video publisher."""
        return list(self._publisher)

    def candidates(self, patterns: Sequence[FullMatch]) -> list[str]:
        """Video topics that one of *patterns* may match (a superset of those they match;
        see :meth:`TopicIndex.candidates`), in :meth:`video_topics` order."""
        return self._index.candidates(patterns)

    def request_frame(self, topic: str) -> bytes:
        """The keyframe request the server sends for video *topic* on its own (the same
        bytes every time: no stamp, no sequence number); kept while the topic is."""
        frame = self._requests.get(topic)
        if frame is None:
            frame = encode_keyframe_request(topic)
            if topic in self._publisher:  # bounded by the topics remembered
                self._requests[topic] = frame
        return frame

    def route(self, topic: str) -> C | None:
        """Where a keyframe request for *topic* goes now, or ``None`` (counted as
        ``no_publisher`` or ``rate_limited``). A returned publisher starts the interval."""
        conn = self._publisher.get(topic)
        if conn is None:
            self._metrics.count_keyframe_request("no_publisher")
            return None
        now = self._clock()
        last = self._last_forward_s.get(topic)
        if last is not None and now - last < self.interval_s:
            self._metrics.count_keyframe_request("rate_limited")
            return None
        self._last_forward_s[topic] = now
        return conn
