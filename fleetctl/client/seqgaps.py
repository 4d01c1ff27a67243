"""Messages lost before the client took them, counted from DDS publication sequence numbers.

What DDS loses never reaches the client's counters: a no_drop topic's burst beyond the
reader's history (the reader keeps the last :data:`~fleetctl.client.ros.qos.NO_DROP_DEPTH`,
a publisher's own KEEP_LAST history overwrites what was not yet acknowledged), a
best-effort camera image one of whose UDP fragments met a full socket buffer. A robot
team saw a no_drop topic arrive with gaps and no line anywhere saying so (20,000 messages
published in 1.5 s, 2,597 arrived). Every sample carries its writer's publication
sequence number (rmw's ``publication_sequence_number``, 1, 2, 3, ... per writer, which
rclpy's take returns), so a jump in it is a count of samples this reader never got.

rclpy's take does not say which writer a sample came from, so the numbers of two
publishers interleave. A gap is therefore counted only when the topic has one publisher
at that moment (asked only when a gap is seen), and a number at or below the last one
(another writer, a restarted one, or a latched writer's stored samples replayed to a new
reader) starts over without counting. Pure: the rclpy side is
:class:`fleetctl.client.ros.qos.AdaptiveSubscription`.
"""

from __future__ import annotations

from collections.abc import Callable


class SequenceGaps:
    """The gaps in one topic's publication sequence numbers.

    Attributes:
        lost: Samples counted as lost so far.
        gaps: Gaps those were found in.
    """

    def __init__(self) -> None:
        self.lost = 0
        self.gaps = 0
        self._last: int | None = None

    def seen(self, sequence: int, publishers: Callable[[], int]) -> int:
        """Take a sample's publication sequence number (0 or less: not known, ignored).

        Args:
            sequence: The sample's publication sequence number.
            publishers: How many publishers the topic has now; called only on a gap.

        Returns:
            The samples this gap lost (0: none, or not attributable to one publisher).
        """
        if sequence <= 0:
            return 0
        last, self._last = self._last, sequence
        if last is None or sequence <= last + 1:
            return 0
        if publishers() != 1:
            return 0
        missed = sequence - last - 1
        self.lost += missed
        self.gaps += 1
        return missed

    def restart(self) -> None:
        """Forget the last number: the reader was recreated (a QoS switch), and what the
        old one missed while the new one matched is the switch's, not a loss to report."""
        self._last = None
