"""fleetctl.client.outagelog: explain once, remind after the interval, quiet between."""

from __future__ import annotations

from fleetctl.client.outagelog import OutageLog, Say, sampled


def test_an_outage_is_explained_once_then_reminded() -> None:
    log = OutageLog(30.0)
    assert log.ended(0.0) is None  # no outage yet
    assert log.failed(100.0, "refused") is Say.EXPLAIN
    assert log.failed(110.0, "refused") is Say.QUIET
    assert log.failed(130.0, "refused") is Say.REMIND
    assert log.failed(131.0, "refused") is Say.QUIET
    assert log.ended(140.0) == (40.0, 4)
    assert log.ended(141.0) is None
    assert log.failed(200.0, "refused") is Say.EXPLAIN  # a new outage: explained again


def test_a_new_reason_is_explained_at_once_in_the_same_outage() -> None:
    log = OutageLog(30.0)
    assert log.failed(0.0, ("ws://a/", "refused")) is Say.EXPLAIN
    assert log.failed(1.0, ("ws://a/", "timed out")) is Say.EXPLAIN
    assert log.failed(2.0, ("ws://a/", "timed out")) is Say.QUIET
    assert log.ended(3.0) == (3.0, 3)  # the outage runs from its first failure


def test_a_per_message_problem_is_logged_first_and_every_thousandth() -> None:
    assert [n for n in range(1, 3002) if sampled(n)] == [1, 1000, 2000, 3000]
