"""Small streaming estimators of the send scheduler (pure, injected time).

- :class:`RateLimiter`: Robofleet Algorithm 1's per-topic rate limit.
- :class:`BusyRate`: link rate as bytes acknowledged over busy time (sizes fragments).
- :class:`WindowedExtremum`: running min/max over a time window (min RTT, max rates).
"""

from __future__ import annotations

from collections import deque


class RateLimiter:
    """Algorithm 1 lines 4-6: at most ``rate_hz`` messages per second per topic.

    Uses a schedule (``next_allowed += period``) rather than "time since last", so a
    10 Hz source limited to 10 Hz is not halved by timer jitter.
    """

    def __init__(self, tolerance: float = 0.05) -> None:
        self._tolerance = tolerance
        self._next_allowed_s: dict[str, float] = {}

    def admit(self, topic: str, rate_hz: float | None, now_s: float) -> bool:
        """True when a message on *topic* at *now_s* (seconds) may be sent."""
        if rate_hz is None:
            return True
        period = 1.0 / rate_hz
        nxt = self._next_allowed_s.get(topic)
        if nxt is not None and now_s < nxt - self._tolerance * period:
            return False
        # Falling behind by more than a period restarts the schedule from now, so an idle
        # topic does not earn a burst.
        late = nxt is None or now_s - nxt > period
        self._next_allowed_s[topic] = (now_s if late or nxt is None else nxt) + period
        return True


class BusyRate:
    """Link rate as bytes acknowledged over busy time, in a sliding window.

    Unlike a max filter of per-ack samples, a sum over time is not fooled by a token
    bucket's burst (a few KB acknowledged in 0.2 ms on a 6 Mbit tbf link looked like
    20 MB/s), so it can size fragments.

    Args:
        window_s: Window length in seconds.
    """

    def __init__(self, window_s: float) -> None:
        self._window_s = window_s
        self._samples: deque[tuple[float, int, float]] = deque()
        self._bytes = 0
        self._busy_s = 0.0

    def add(self, now_s: float, acked_bytes: int, busy_s: float) -> None:
        """*acked_bytes* were acknowledged after *busy_s* seconds of waiting, at *now_s*."""
        self._samples.append((now_s, acked_bytes, busy_s))
        self._bytes += acked_bytes
        self._busy_s += busy_s
        while len(self._samples) > 1 and self._samples[0][0] < now_s - self._window_s:
            _, b, d = self._samples.popleft()
            self._bytes -= b
            self._busy_s -= d

    def rate(self) -> float:
        """Bytes per second, 0 before the first sample."""
        return self._bytes / self._busy_s if self._busy_s > 0 else 0.0

    @property
    def bytes(self) -> int:
        """Bytes acknowledged within the window."""
        return self._bytes

    def clear(self) -> None:
        """Forget all samples."""
        self._samples.clear()
        self._bytes, self._busy_s = 0, 0.0

    def scale(self, factor: float) -> None:
        """Count every sample's bytes *factor* times (the unit of a byte changed)."""
        self._samples = deque((t, int(b * factor), d) for t, b, d in self._samples)
        self._bytes = sum(b for _, b, _ in self._samples)


class WindowedExtremum:
    """Running min or max of samples over a sliding time window, O(1) amortized.

    A monotonic deque: a new sample evicts older ones it dominates, so the front is the
    extremum; samples older than the window expire from the front (the newest is kept).

    Args:
        window_s: Window length in seconds.
        keep_max: True for a max filter, False for a min filter.
    """

    def __init__(self, window_s: float, *, keep_max: bool) -> None:
        self._window_s = window_s
        self._sign = 1.0 if keep_max else -1.0
        self._samples: deque[tuple[float, float]] = deque()

    def add(self, now_s: float, value: float) -> None:
        """Add a sample taken at *now_s*."""
        key = self._sign * value
        while self._samples and self._sign * self._samples[-1][1] <= key:
            self._samples.pop()
        self._samples.append((now_s, value))
        self._expire(now_s)

    def value(self, now_s: float | None, default: float) -> float:
        """The extremum (expiring old samples first when *now_s* is given)."""
        if now_s is not None:
            self._expire(now_s)
        return self._samples[0][1] if self._samples else default

    def clear(self) -> None:
        """Forget all samples."""
        self._samples.clear()

    def scale(self, factor: float) -> None:
        """Multiply every sample by *factor* (> 0: the order of the samples stays)."""
        self._samples = deque((t, v * factor) for t, v in self._samples)

    def _expire(self, now_s: float) -> None:
        while len(self._samples) > 1 and self._samples[0][0] < now_s - self._window_s:
            self._samples.popleft()
