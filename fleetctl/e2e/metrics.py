"""Pure analysis of e2e samples: latency statistics, dropout recovery, delivery order.

Times are seconds relative to the run's start unless a name says ``_ns``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fleetctl.e2e.samples import Sample


@dataclass(frozen=True)
class LatencyStats:
    """Latency summary of one set of samples (milliseconds; NaN when empty)."""

    count: int
    p50_ms: float
    p90_ms: float
    p99_ms: float
    max_ms: float

    @staticmethod
    def of(samples: Sequence[Sample]) -> LatencyStats:
        """Statistics of *samples*."""
        if not samples:
            nan = math.nan
            return LatencyStats(0, nan, nan, nan, nan)
        lat = np.array([s.latency_ms for s in samples])
        p50, p90, p99 = np.percentile(lat, [50, 90, 99])
        return LatencyStats(len(lat), float(p50), float(p90), float(p99), float(lat.max()))


def by_topic(samples: Sequence[Sample]) -> dict[str, list[Sample]]:
    """Samples grouped by topic, each in receipt order."""
    out: dict[str, list[Sample]] = {}
    for s in sorted(samples, key=lambda s: s.recv_time_ns):
        out.setdefault(s.topic, []).append(s)
    return out


def recovery_s(
    samples: Sequence[Sample], cut_start_ns: int, restore_ns: int, *,
    factor: float = 2.0, hold_s: float = 1.0,
) -> float:
    """Seconds from *restore_ns* until latency is back under *factor* x its pre-cut median.

    "Back" means: the first receipt time t >= restore of a message under the bound such
    that the median latency of the messages received in [t, t + hold_s] is under the bound
    too (and the run lasts until t + hold_s). A median, not every message: periodic spikes
    the link shows before the cut as well (a small message behind a large one's fragment)
    do not count as "not recovered", a backlog still draining does. ``inf`` when that never
    happens in the samples (or there was no traffic before the cut).
    """
    before = [s.latency_ms for s in samples if s.recv_time_ns < cut_start_ns]
    if not before:
        return math.inf
    bound_ms = factor * float(np.median(before))
    after = sorted((s for s in samples if s.recv_time_ns >= restore_ns),
                   key=lambda s: s.recv_time_ns)
    hold_ns = int(hold_s * 1e9)
    for i, first in enumerate(after):
        if first.latency_ms >= bound_ms:
            continue
        window_end = first.recv_time_ns + hold_ns
        if after[-1].recv_time_ns < window_end:
            break  # not enough run left to show it holds
        window = [s.latency_ms for s in after[i:] if s.recv_time_ns <= window_end]
        if float(np.median(window)) < bound_ms:
            return (first.recv_time_ns - restore_ns) / 1e9
    return math.inf


def publish_period_ns(samples: Sequence[Sample]) -> float:
    """A periodic topic's publish period from its samples' stamps (ns; NaN if unknown).

    Per consecutive pair in sequence order, the publish-time step over the ``seq`` step, so
    a message lost in between does not count as a longer period; the median of those.
    """
    ordered = sorted(samples, key=lambda s: s.seq)
    steps = [(b.publish_time_ns - a.publish_time_ns) / (b.seq - a.seq)
             for a, b in itertools.pairwise(ordered) if b.seq > a.seq]
    return float(np.median(steps)) if steps else math.nan


def recovery_limit_s(samples: Sequence[Sample], cut_start_ns: int, restore_ns: int) -> float:
    """The soonest any stack could meet :func:`recovery_s` after this restore (seconds).

    That is the topic's first publish at or after the restore, plus its pre-cut median
    latency: a message published before the restore waited out the cut and cannot be
    under 2x that median. The publish time comes from the topic's timer, not from what
    was delivered (the stack under test may have lost that message): the first message
    published after the restore that did arrive, moved back by whole periods while it
    stays at or after the restore. NaN without samples both before the cut and after the
    restore.
    """
    before = [s for s in samples if s.recv_time_ns < cut_start_ns]
    later = [s.publish_time_ns for s in samples if s.publish_time_ns >= restore_ns]
    period = publish_period_ns(before)
    if not before or not later or not period > 0:
        return math.nan
    first = min(later)
    earliest = first - math.floor((first - restore_ns) / period) * period
    median_ms = float(np.median([s.latency_ms for s in before]))
    return (earliest - restore_ns) / 1e9 + median_ms / 1e3


@dataclass(frozen=True)
class OrderCheck:
    """Delivery of a no_drop topic: every sequence number once, in order."""

    received: int
    missing: int
    out_of_order: int
    duplicates: int

    @property
    def ok(self) -> bool:
        """True when nothing is missing, duplicated or out of order."""
        return self.missing == 0 and self.out_of_order == 0 and self.duplicates == 0


def check_order(samples: Sequence[Sample], expected_seqs: Sequence[int]) -> OrderCheck:
    """Compare received sequence numbers (in receipt order) with those published."""
    got = [s.seq for s in sorted(samples, key=lambda s: s.recv_time_ns)]
    inversions = sum(1 for a, b in itertools.pairwise(got) if b < a)
    return OrderCheck(
        received=len(got),
        missing=len(set(expected_seqs) - set(got)),
        out_of_order=inversions,
        duplicates=len(got) - len(set(got)),
    )


def throughput_bit_s(samples: Sequence[Sample]) -> float:
    """Received payload rate over the samples' span (bits per second; 0 if under 2)."""
    if len(samples) < 2:
        return 0.0
    times = [s.recv_time_ns for s in samples]
    span_s = (max(times) - min(times)) / 1e9
    return sum(s.size_bytes for s in samples) * 8 / span_s if span_s > 0 else 0.0
