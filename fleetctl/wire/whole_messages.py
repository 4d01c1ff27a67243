"""Whole messages out of a stream of received frames: text skipped, fragments reassembled.

Every plain reader of a relay (a test's viewer, a benchmark's consumer) does the same thing
before it can use a frame: skip the text frames (the relay's JSON events), feed each binary
frame through a :class:`~fleetctl.wire.fragments.Reassembler` and take what comes out whole.
:func:`whole_messages` is that loop over any async iterable of frames; a websockets
connection is one. It does no I/O of its own and imports neither asyncio nor websockets
(this package never does): a deadline is the caller's (``asyncio.timeout`` around the
loop, or a source that stops at one).

Not for a reader that takes each frame inside the read that brought it
(:mod:`fleetctl.frame_sink`: the e2e consumer): it feeds its Reassembler frame by frame.
"""

from __future__ import annotations

import time
from collections.abc import AsyncGenerator, AsyncIterable
from contextlib import aclosing

from fleetctl.wire.fragments import Reassembler

# The default reassembler's bounds: as the e2e consumer's and the robot client's (64 MiB).
DEFAULT_MAX_BYTES = 64 * 1024 * 1024
DEFAULT_TIMEOUT_S = 10.0


async def whole_messages(frames: AsyncIterable[str | bytes],
                         reassembler: Reassembler | None = None) -> AsyncGenerator[bytes, None]:
    """Yield the whole binary messages of *frames*, in the order they complete.

    A frame that is not a fragment is yielded as it came; a fragmented message when its
    last fragment arrives. What the reassembler drops (superseded, timed out, over its
    bounds, malformed) is counted in ``reassembler.stats``, not raised. When *frames* ends
    in the middle of a message, that partial message stays in the reassembler
    (``pending_messages``) and nothing more is yielded.

    Args:
        frames: Received frames: ``str`` (text frames, skipped) or ``bytes``. A websockets
            connection ends its iteration at a normal close and raises
            ``ConnectionClosedError`` at any other.
        reassembler: Reassembles the fragments (its ``stats`` say what it dropped). None: a
            new one bounded at :data:`DEFAULT_MAX_BYTES` and :data:`DEFAULT_TIMEOUT_S`.

    Raises:
        WireError: A binary frame has no readable fleetctl metadata.
    """
    if reassembler is None:
        reassembler = Reassembler(DEFAULT_MAX_BYTES, DEFAULT_TIMEOUT_S)
    async for frame in frames:
        if isinstance(frame, str):
            continue
        whole = reassembler.feed(frame, time.monotonic())
        if whole is not None:
            yield whole


async def first_whole_messages(frames: AsyncIterable[str | bytes], count: int,
                               reassembler: Reassembler | None = None) -> list[bytes]:
    """The first *count* whole messages of *frames* (:func:`whole_messages`).

    Waits as long as *frames* does: bound it with ``asyncio.timeout`` or ``wait_for``.

    Raises:
        ValueError: *count* is below 1.
        EOFError: *frames* ended before *count* whole messages; the message says how many
            came.
        WireError: A binary frame has no readable fleetctl metadata.
    """
    if count < 1:
        raise ValueError(f"count must be at least 1, not {count}")
    wholes: list[bytes] = []
    async with aclosing(whole_messages(frames, reassembler)) as messages:
        async for whole in messages:
            wholes.append(whole)
            if len(wholes) == count:
                return wholes
    raise EOFError(f"the frames ended after {len(wholes)} of {count} whole messages")
