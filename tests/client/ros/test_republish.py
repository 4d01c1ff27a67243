"""The republishing writers' depth and the count of no_drop bursts deeper than it
(fleetctl.client.ros.republish; pure, with a clock moved by hand)."""

from __future__ import annotations

import pytest

pytest.importorskip("rclpy")

from fleetctl.client.ros.republish import (
    ACK_WINDOW_S,
    BIG_DROPPABLE_BYTES,
    DEEP_DEPTH,
    MAX_WATCHED_TOPICS,
    SHALLOW_DEPTH,
    BurstWatch,
    depth_for,
)
from tests.support import ManualClock


def test_deep_unless_a_big_droppable_frame() -> None:
    assert depth_for(no_drop=True, frame_bytes=10 * BIG_DROPPABLE_BYTES) == DEEP_DEPTH
    assert depth_for(no_drop=False, frame_bytes=BIG_DROPPABLE_BYTES) == DEEP_DEPTH
    assert depth_for(no_drop=False, frame_bytes=BIG_DROPPABLE_BYTES + 1) == SHALLOW_DEPTH


def test_a_burst_deeper_than_the_history_within_the_ack_window_is_at_risk() -> None:
    clock = ManualClock()
    watch = BurstWatch(clock)
    assert not any(watch.published("/e", 10) for _ in range(10))
    assert watch.published("/e", 10)  # the 11th: the 10 before it are not acked yet
    clock.now_s += ACK_WINDOW_S  # the oldest of the last 10 is acknowledged by now
    assert not watch.published("/e", 10)
    assert not watch.published("/other", 10)  # per topic


def test_a_steady_stream_within_the_depth_is_never_at_risk() -> None:
    clock = ManualClock()
    watch = BurstWatch(clock)
    at_risk = 0
    for _ in range(1000):  # 3 Hz with depth 10: 9 messages per ack window
        clock.now_s += 1 / 3
        at_risk += watch.published("/e", 10)
    assert at_risk == 0


def test_the_topics_watched_are_bounded() -> None:
    watch = BurstWatch(ManualClock())
    for i in range(MAX_WATCHED_TOPICS + 10):
        watch.published(f"/t{i}", 2)
    assert len(watch._recent) == MAX_WATCHED_TOPICS
