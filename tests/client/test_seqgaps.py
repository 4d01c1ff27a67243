"""Gaps in a topic's DDS publication sequence numbers: messages lost before the client."""

from __future__ import annotations

from fleetctl.client.seqgaps import SequenceGaps


def one() -> int:
    return 1


def test_a_jump_of_the_one_publisher_counts_what_it_skipped() -> None:
    gaps = SequenceGaps()
    assert [gaps.seen(n, one) for n in (1, 2, 3, 7, 8, 20)] == [0, 0, 0, 3, 0, 11]
    assert (gaps.lost, gaps.gaps) == (14, 2)


def test_unknown_numbers_are_ignored() -> None:
    gaps = SequenceGaps()
    assert [gaps.seen(n, one) for n in (0, 5, 0, -1, 6)] == [0, 0, 0, 0, 0]
    assert gaps.lost == 0


def test_a_number_at_or_below_the_last_starts_over_without_counting() -> None:
    # Another or a restarted writer, or a latched writer's stored sample replayed.
    gaps = SequenceGaps()
    assert [gaps.seen(n, one) for n in (500, 501, 1, 2, 2, 5)] == [0, 0, 0, 0, 0, 2]
    assert gaps.lost == 2


def test_interleaved_publishers_are_not_counted() -> None:
    """rclpy's take does not say which writer a sample came from: with two publishers a
    jump is theirs interleaving, not a loss. The count is asked only on a jump."""
    asked: list[int] = []

    def two() -> int:
        asked.append(2)
        return 2

    gaps = SequenceGaps()
    assert [gaps.seen(n, two) for n in (1, 2, 900, 3, 901, 4)] == [0] * 6
    assert gaps.lost == 0 and len(asked) == 2  # at 2 -> 900 and 3 -> 901


def test_a_restart_forgets_the_last_number() -> None:
    """A QoS switch recreates the reader: what the old one missed meanwhile is the
    switch's (documented), not reported as DDS losses."""
    gaps = SequenceGaps()
    gaps.seen(10, one)
    gaps.restart()
    assert gaps.seen(15, one) == 0 and gaps.lost == 0
    assert gaps.seen(17, one) == 1
