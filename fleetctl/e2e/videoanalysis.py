"""Pure analysis of the video topic in the e2e scenarios (issue 18).

The consumer's samples of a video topic say, per frame, its wire ``seq``, whether it is a
keyframe and when (if at all) the consumer's decoder showed it (:mod:`.videoview`). Here,
independently of that decoder:

- **broken references**: frames are walked in arrival order; a keyframe starts an intact
  chain, a delta frame keeps it intact only when its wire ``seq`` follows the previous
  frame's. A frame shown while its chain is broken is a frame drawn from a broken
  reference (the bar: none).
- **back after the restore**: the first frame the camera took after the link's restore
  that was shown, in seconds after the restore (the bar: 1 s).
- **bitrate**: the video's bytes per second over time, to compare with the link's rate.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from fleetctl.e2e.analysis import crit
from fleetctl.e2e.samples import Sample


@dataclass(frozen=True)
class Chain:
    """What the walk over a video topic's frames found.

    Attributes:
        frames: Frames received.
        keyframes: Keyframes among them.
        shown: Frames the decoder showed.
        gaps: Places where the wire ``seq`` jumped (frames lost or dropped on the way).
        broken_shown: Frames shown although a frame they depend on was missing.
    """

    frames: int
    keyframes: int
    shown: int
    gaps: int
    broken_shown: int


def chain(samples: Sequence[Sample]) -> Chain:
    """Walk one consumer's frames of one video topic in arrival order."""
    frames = sorted((s for s in samples if s.is_video),
                    key=lambda s: (s.recv_time_ns, s.wire_seq or 0))
    intact, last, gaps, broken, keyframes, shown = False, None, 0, 0, 0, 0
    for s in frames:
        follows = last is not None and s.wire_seq == last + 1
        if last is not None and not follows:
            gaps += 1
        last = s.wire_seq
        if s.keyframe:
            keyframes += 1
            intact = True
        elif not follows:
            intact = False
        if s.shown_ns is not None:
            shown += 1
            if not intact:
                broken += 1
    return Chain(len(frames), keyframes, shown, gaps, broken)


def first_shown_after_s(samples: Sequence[Sample], restore_ns: int,
                        fresh: bool = False) -> float:
    """Seconds from *restore_ns* to the first frame shown at or after it (inf: none).

    With *fresh*, only frames the camera took at or after the restore count: the live
    picture is back (a frame from before the cut, still in flight, can be shown first).
    """
    shown = [s.shown_ns for s in samples if s.shown_ns is not None and s.shown_ns >= restore_ns
             and (not fresh or s.publish_time_ns >= restore_ns)]
    return (min(shown) - restore_ns) / 1e9 if shown else math.inf


def bitrate_line(samples: Sequence[Sample], t0_ns: int, end_ns: int,
                 bin_s: float = 1.0) -> list[list[float]]:
    """``[xs, ys]``: the video's received Mbit/s per *bin_s* window (x: window middle, s
    from *t0_ns*), frames counted by their receipt time."""
    bins = max(1, math.ceil((end_ns - t0_ns) / 1e9 / bin_s))
    totals = [0] * bins
    for s in samples:
        i = int((s.recv_time_ns - t0_ns) / 1e9 / bin_s)
        if 0 <= i < bins:
            totals[i] += s.size_bytes
    return [[round((i + 0.5) * bin_s, 3) for i in range(bins)],
            [round(b * 8 / bin_s / 1e6, 4) for b in totals]]


def mean_mbit_s(samples: Sequence[Sample], start_ns: int, end_ns: int) -> float:
    """Mean received Mbit/s of the frames that arrived in ``[start_ns, end_ns)``."""
    size = sum(s.size_bytes for s in samples if start_ns <= s.recv_time_ns < end_ns)
    return size * 8 / max(1e-9, (end_ns - start_ns) / 1e9) / 1e6


def dropout_criteria(topic: str, samples: Sequence[Sample],
                     restore_ns: int) -> tuple[list[dict[str, Any]], list[str]]:
    """The dropout scenario's video rows: back within 1 s, never from a broken reference."""
    c = chain(samples)
    back = first_shown_after_s(samples, restore_ns, fresh=True)
    criteria = [
        crit(f"video {topic}: first live frame shown after the restore (s)", back, 1.0,
             back <= 1.0),
        crit(f"video {topic}: frames shown from a broken reference", c.broken_shown, 0,
             c.broken_shown == 0 and c.shown > 0),
    ]
    notes = [f"video {topic}: {c.frames} frames received ({c.keyframes} keyframes), "
             f"{c.shown} shown, {c.frames - c.shown} refused, {c.gaps} seq gaps; first "
             f"frame of any age shown {first_shown_after_s(samples, restore_ns):.3f} s "
             "after the restore"]
    return criteria, notes
