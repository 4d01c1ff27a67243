"""Whether the robot's wall clock agrees with its server's, from the upgrade's ``Date``.

Every frame carries the robot's wall clock (``publish_time_ns``), and the fleet's pages
judge how old a robot's data is by it: a robot without NTP (no RTC, no internet, a clock
hours off after a battery change) had its live data shown as "N s old" on every page, and
nothing on the robot said why. The relay's WebSocket upgrade answer carries an HTTP
``Date`` (RFC 9110 section 6.6.1: whole seconds, the time the answer was made), so each
connection gives one reading of the offset at no cost. Pure: :class:`ClockCheck` takes
the header and the robot's clock and says what to log; the link logs it.
"""

from __future__ import annotations

import email.utils
from dataclasses import dataclass

# Beyond the Date's own second, this much either way (a round trip, the pages' 1 s "old"
# note) is taken for a clock in step.
TOLERANCE_S = 1.0


def date_offset_s(date_header: str | None, now_s: float) -> float | None:
    """The robot's clock minus the server's by *date_header* (positive: the robot is
    ahead), 0.0 when within the header's second and :data:`TOLERANCE_S`; None without a
    readable header."""
    if not date_header:
        return None
    try:
        server = email.utils.parsedate_to_datetime(date_header)
    except (TypeError, ValueError):
        return None
    if server.tzinfo is None:  # "-0000": RFC 5322's unknown zone, HTTP says GMT
        return None
    # The server's clock read somewhere in its Date's second: half a second on average.
    offset = now_s - server.timestamp() - 0.5
    return 0.0 if abs(offset) <= 0.5 + TOLERANCE_S else offset


@dataclass
class ClockCheck:
    """The offset readings of one link: warn when it is off, once until it agrees again.

    Attributes:
        offset_s: The last reading (0.0: in step); None before any reading.
    """

    offset_s: float | None = None
    _warned: bool = False

    def reading(self, date_header: str | None, now_s: float) -> tuple[str, float] | None:
        """Take one connection's ``Date``; return ``("off", offset_s)`` the first time the
        clock is off, ``("agrees", 0.0)`` the first time it agrees after that, else None."""
        offset = date_offset_s(date_header, now_s)
        if offset is None:
            return None
        off = offset != 0.0
        self.offset_s = offset
        if off and not self._warned:
            self._warned = True
            return "off", offset
        if not off and self._warned:
            self._warned = False
            return "agrees", offset
        return None


def clock_line(kind: str, offset_s: float, url: str) -> str:
    """The log line of a :meth:`ClockCheck.reading`."""
    if kind == "agrees":
        return f"this robot's wall clock agrees with {url}'s again"
    lag = abs(offset_s)
    seen = (f"the fleet's pages show its live data as about {lag:.0f} s old" if offset_s < 0
            else f"its data is stamped about {lag:.0f} s in the future")
    return (f"this robot's wall clock is about {lag:.0f} s "
            f"{'behind' if offset_s < 0 else 'ahead of'} {url}'s (the Date of its upgrade "
            f"answer): frames carry the robot's clock, so {seen}; sync it (chrony or "
            "systemd-timesyncd; a robot without internet can use the fleet machine as its "
            "NTP server)")
