"""When to log a problem that repeats: a connect that failed again, a bad frame again.

One :class:`OutageLog` per kind of outage the link reports (``bind_address`` on no
interface, the server not reachable), so that a robot started hours before its tunnel or
its server logs a few lines, not a WARNING per attempt; :func:`sampled` for problems
counted per message.
"""

from __future__ import annotations

import enum


class Say(enum.Enum):
    """What a failed attempt should log."""

    EXPLAIN = "explain"  # the first of an outage, or a new reason: the WARNING with hints
    REMIND = "remind"  # a reminder interval since the last WARNING
    QUIET = "quiet"  # in between: DEBUG


class OutageLog:
    """One kind of outage: since when, how many attempts, when last said, and why.

    Args:
        reminder_interval_s: Seconds between two reminders of one outage.
    """

    def __init__(self, reminder_interval_s: float) -> None:
        self.reminder_interval_s = reminder_interval_s
        self.since_s: float | None = None  # None: no outage
        self.attempts = 0
        self._warned_s = 0.0
        self._reason: object = None  # what the last explanation was about

    def failed(self, now_s: float, reason: object) -> Say:
        """Count a failed attempt at *now_s*; a *reason* other than the last explained is
        explained at once (a new URL, a new error)."""
        self.attempts += 1
        if self.since_s is None:
            self.since_s = now_s
        if reason != self._reason:
            self._reason, self._warned_s = reason, now_s
            return Say.EXPLAIN
        if now_s - self._warned_s >= self.reminder_interval_s:
            self._warned_s = now_s
            return Say.REMIND
        return Say.QUIET

    def ended(self, now_s: float) -> tuple[float, int] | None:
        """End the outage, if one ran: its length (seconds) and its failed attempts."""
        if self.since_s is None:
            return None
        ended = (now_s - self.since_s, self.attempts)
        self.since_s, self.attempts, self._reason = None, 0, None
        return ended


LOG_EVERY = 1000


def sampled(count: int) -> bool:
    """Whether the *count*-th occurrence of a per-message problem is logged: the first
    and every :data:`LOG_EVERY`-th (a broken sender must not write a line per message)."""
    return count == 1 or count % LOG_EVERY == 0
