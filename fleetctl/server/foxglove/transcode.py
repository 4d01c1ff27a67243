"""Frames to CDR once per frame, however many viewers receive it.

Every Foxglove viewer's scheduler holds the *same* ``bytes`` object the relay routed (the
core pushes one frame object to every receiver). The first viewer whose writer pops it
has it transcoded; the others find the result by the frame's identity. Only popped frames are
transcoded: a frame superseded in every viewer's latest-per-topic slot costs nothing, and
topics nobody subscribed to never reach a viewer at all.

The cache is bounded in entries and bytes (oldest evicted first). An entry keeps a
reference to its frame, so ``id(frame)`` cannot be reused by another object while the
entry lives. A viewer that pops a frame after its entry was evicted transcodes it again:
the cost of a very slow viewer, paid by that viewer's writer, never a wrong answer for
a whole message. Fragments are reassembled per topic by the first viewer that pops each
one; a viewer popping a fragment whose entry was evicted gets nothing for it (the
fragment was already fed).

Threads: :meth:`SharedTranscoder.convert` runs on the one conversion thread
(:mod:`fleetctl.server.foxglove.offload`), never on the event loop; the loop only looks
up results (:meth:`SharedTranscoder.cached`). A lock guards the cache's dict, never a
conversion, so a lookup never waits for one.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import NamedTuple

from fleetctl.wire.codec import Codec
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import FRAGMENT_TYPE
from fleetctl.wire.metadata import read_root
from fleetctl.wire.ros2msg import FrameTranscoder

# Why these: a viewer popping within a few hundred frames of the fastest one (the usual
# case: all viewers are served by the same event loop) hits the cache.
MAX_ENTRIES = 512
MAX_CACHED_BYTES = 64 * 1024 * 1024


class Converted(NamedTuple):
    """One message as a Foxglove viewer gets it.

    Attributes:
        type: Its ROS 2 type (``sensor_msgs/msg/LaserScan``).
        cdr: CDR bytes (with the 4-byte encapsulation header).
        receive_time_ns: Server wall clock when it was transcoded, ns since the epoch.
    """

    type: str
    cdr: bytes
    receive_time_ns: int


class NotCached:
    """The type of :data:`NOT_CACHED` (``None`` is a result: nothing to send)."""

    __slots__ = ()


NOT_CACHED = NotCached()


class SharedTranscoder:
    """The frame -> CDR cache shared by every Foxglove viewer of a server.

    Args:
        codec: Decodes the frames.
        max_message_bytes: Largest reassembled or decompressed frame, bytes.
        clock: Monotonic clock, seconds (reassembly timeouts).
        wall_ns: Wall clock, ns since the epoch (receive timestamps).
    """

    def __init__(self, codec: Codec, max_message_bytes: int,
                 clock: Callable[[], float] = time.monotonic,
                 wall_ns: Callable[[], int] = time.time_ns) -> None:
        self._transcoder = FrameTranscoder(codec, max_message_bytes)
        self._clock = clock
        self._wall_ns = wall_ns
        self._cache: OrderedDict[int, tuple[bytes, Converted | None]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()  # the cache's dict: the loop reads, the worker writes
        self.transcoded = 0  # frames fed to the transcoder (the work done)
        self.hits = 0
        self.failed = 0  # frames that do not transcode (malformed, unknown type)

    def cached(self, frame: bytes) -> Converted | NotCached | None:
        """The result for *frame* if it was converted already (counted as a hit), else
        :data:`NOT_CACHED`. Never converts: safe on the event loop."""
        with self._lock:
            entry = self._cache.get(id(frame))
            if entry is not None and entry[0] is frame:
                self.hits += 1
                return entry[1]
        return NOT_CACHED

    def convert(self, frame: bytes) -> Converted | None:
        """CDR of the message *frame* carries or completes; ``None`` for a fragment that
        completes nothing and for a frame that does not transcode (counted). Called from
        one thread at a time (the reassembly state is not locked)."""
        hit = self.cached(frame)
        if not isinstance(hit, NotCached):
            return hit
        result = self._feed(frame)
        with self._lock:
            self._remember(frame, result)
        return result

    def _feed(self, frame: bytes) -> Converted | None:
        self.transcoded += 1
        try:
            read = read_root(frame)
            # Fragments of one topic reassemble together, whoever popped them first.
            sender = read[0].topic if read[0].type == FRAGMENT_TYPE else None
            done = self._transcoder.feed(sender, frame, self._clock(), read)
        except WireError:
            self.failed += 1
            return None
        return None if done is None else Converted(done.type, done.cdr, self._wall_ns())

    def _remember(self, frame: bytes, result: Converted | None) -> None:
        stale = self._cache.pop(id(frame), None)  # an id reused by a newer frame
        if stale is not None:
            self._bytes -= _size(*stale)
        self._cache[id(frame)] = (frame, result)
        self._bytes += _size(frame, result)
        while len(self._cache) > MAX_ENTRIES or (self._bytes > MAX_CACHED_BYTES
                                                  and len(self._cache) > 1):
            self._bytes -= _size(*self._cache.popitem(last=False)[1])


def _size(frame: bytes, result: Converted | None) -> int:
    return len(frame) + (len(result.cdr) if result is not None else 0)
