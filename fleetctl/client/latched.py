"""The robot's copy of the last latched frame of each topic, re-sent after a reconnect.

A latched topic (``/map``, ``/tf_static``, ``/robot_description``) is published once. Its
frame is droppable like any sensor frame (the entry decides no_drop), and on a disconnect
the link drops a droppable frame it had partly sent or not yet seen acknowledged
(fleetctl.client.scheduler), so a map sent just before a radio dropout would never reach
the fleet: nothing publishes it again. The server's store (docs/server.md) only helps once
it has the frame, and it lives in memory. So the client keeps the last encoded frame of
each latched topic and offers it again on every new connection; receivers keep the last
one, so a copy that did arrive is harmless.

Pure bookkeeping (no I/O, no rclpy), thread-safe: frames are put from the rclpy
executor's thread or the loop's and taken from either.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Generic, TypeVar

# Maps compress ~50x; 16 MiB holds the last message of many latched topics. A frame larger
# than this alone (a huge uncompressible latched cloud) is not kept (counted).
DEFAULT_MAX_BYTES = 16 * 1024 * 1024

S = TypeVar("S")


@dataclass
class LatchedStats:
    """Counters of a :class:`LatchedFrames`.

    Attributes:
        kept: frames stored (a newer frame of a topic replaces the older one).
        evicted: frames dropped, oldest first, to stay under the byte bound.
        too_large: frames not kept because they alone exceed the bound.
    """

    kept: int = 0
    evicted: int = 0
    too_large: int = 0


class LatchedFrames(Generic[S]):
    """The last frame of each latched topic, bounded in total bytes.

    Args:
        max_bytes: Upper bound of the stored frames' total size (bytes).
    """

    def __init__(self, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
        self.max_bytes = max_bytes
        self.stats = LatchedStats()
        self._frames: OrderedDict[str, tuple[S, bytes | memoryview]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def total_bytes(self) -> int:
        """Bytes held now."""
        return self._bytes

    def put(self, topic: str, spec: S, frame: bytes | memoryview) -> None:
        """Keep *frame* as the last one of *topic* (with *spec*, what it is sent with).

        The least recently put topics are evicted first when the bound is exceeded.
        """
        size = len(frame)
        with self._lock:
            old = self._frames.pop(topic, None)
            if old is not None:
                self._bytes -= len(old[1])
            if size > self.max_bytes:
                self.stats.too_large += 1
                return
            while self._frames and self._bytes + size > self.max_bytes:
                _, (_, dropped) = self._frames.popitem(last=False)
                self._bytes -= len(dropped)
                self.stats.evicted += 1
            self._frames[topic] = (spec, frame)
            self._bytes += size
            self.stats.kept += 1

    def forget(self, topic: str) -> None:
        """Drop *topic*'s frame (a newer message of it is not latched)."""
        with self._lock:
            old = self._frames.pop(topic, None)
            if old is not None:
                self._bytes -= len(old[1])

    def snapshot(self) -> list[tuple[str, S, bytes | memoryview]]:
        """Every kept frame, oldest first: ``(topic, spec, frame)``."""
        with self._lock:
            return [(topic, spec, frame) for topic, (spec, frame) in self._frames.items()]

    def __len__(self) -> int:
        return len(self._frames)

    def __contains__(self, topic: object) -> bool:
        # No lock: one dict lookup is atomic, and a caller racing a put sees either state.
        return topic in self._frames
