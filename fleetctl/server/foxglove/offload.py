"""Frames to CDR off the relay's event loop.

Why: converting a frame to CDR is Python work proportional to its fields, 17.5 ms for a
2,000-pose ``nav_msgs/Path`` and 37 ms for a 300-marker ``MarkerArray`` (more on a busy
host). On the loop, every other connection of the relay waited that long: robots' acks,
other viewers, the web page (docs/foxglove.md, "Heavy topics").

How: one conversion thread for the process. Each Foxglove writer hands it the frames of
one batch it popped and awaits them, so a viewer's frames keep their order, and at most
one batch per viewer waits: the work waiting is bounded by the open Foxglove connections
(the relay's connection limit), never by the frame rate. While a viewer's batch converts,
its scheduler goes on taking frames as it does for a slow socket: the latest per topic,
the older ones superseded and counted (the adapter says so once per topic).

Why one thread: the conversion holds the GIL, so a second thread would not convert faster;
it would only take the GIL from the loop more often. Why the switch interval: a thread
running Python keeps the GIL up to ``sys.getswitchinterval()`` when the loop wants it
(Python's 5 ms), and the loop gives it up at every socket call and every wait; 0.5 ms, as
the robot's client has for the same reason (fleetctl.gilswitch).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from fleetctl.gilswitch import tune_gil
from fleetctl.server.foxglove.transcode import Converted, NotCached, SharedTranscoder

log = logging.getLogger("fleetctl.server.foxglove")

_executor: ThreadPoolExecutor | None = None
_executor_lock = threading.Lock()


def executor() -> ThreadPoolExecutor:
    """The process's conversion thread (created, and the GIL tuned, on first use)."""
    global _executor
    with _executor_lock:
        if _executor is None:
            tune_gil()
            _executor = ThreadPoolExecutor(1, thread_name_prefix="fleetctl-foxglove-cdr")
        return _executor


class Batch:
    """The results of one writer batch, in the frames' order.

    Attributes:
        results: One per frame: its :class:`Converted`, or ``None`` (nothing to send).
        converted: Frames the thread converted for this batch (0: all from the cache).
        seconds: Wall time the thread spent on them.
    """

    __slots__ = ("converted", "results", "seconds")

    def __init__(self, results: list[Converted | None], converted: int,
                 seconds: float) -> None:
        self.results = results
        self.converted = converted
        self.seconds = seconds


async def convert(transcoder: SharedTranscoder, frames: list[bytes]) -> Batch:
    """Convert *frames* (one writer's batch, in order) on the conversion thread; those
    already in the shared cache are answered at once, on the loop."""
    looked = [transcoder.cached(f) for f in frames]
    todo = [f for f, r in zip(frames, looked, strict=True) if isinstance(r, NotCached)]
    done: list[Converted | None] = []
    seconds = 0.0
    if todo:
        loop = asyncio.get_running_loop()
        done, seconds = await loop.run_in_executor(executor(), _convert_all, transcoder, todo)
    answers = iter(done)
    results = [next(answers) if isinstance(r, NotCached) else r for r in looked]
    return Batch(results, len(todo), seconds)

def _convert_all(transcoder: SharedTranscoder,
                 frames: list[bytes]) -> tuple[list[Converted | None], float]:
    start = time.perf_counter()
    out: list[Converted | None] = []
    for frame in frames:  # in order: a fragment is fed before the next one of its message
        try:
            out.append(transcoder.convert(frame))
        except Exception:  # a bug costs this frame, not the viewer's writer
            log.exception("a frame did not convert to CDR for Foxglove")
            out.append(None)
    return out, time.perf_counter() - start
