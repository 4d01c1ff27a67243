"""The scheduler after an outage (issue 19): stale held messages are dropped."""

from __future__ import annotations

import pytest

from fleetctl.client.scheduler import Scheduler, SchedulerConfig
from tests.client.test_scheduler import FakeLink, fake_split


def make(**kw: object) -> Scheduler:
    cfg = SchedulerConfig(**{"max_fragment_bytes": 100, **kw})  # type: ignore[arg-type]
    return Scheduler(cfg, split=fake_split)


def offer_every(s: Scheduler, topic: str, period_s: float, until_s: float,
                start_s: float = 0.0, no_drop: bool = False) -> None:
    """Offer *topic* every *period_s* from *start_s* up to *until_s* (its period is
    measured from these)."""
    n = 0
    while start_s + n * period_s <= until_s + 1e-9:
        now = start_s + n * period_s
        s.offer(topic, f"{topic}@{now:.2f}".encode(), now, priority=1.0, no_drop=no_drop)
        n += 1


def test_after_an_outage_every_held_message_is_dropped_and_counted() -> None:
    s = make()
    offer_every(s, "/scan", 0.1, 1.0)
    offer_every(s, "/image", 0.5, 1.0)
    assert s.drop_stale(1.02, after_outage=True) == 2
    assert FakeLink(s).drain(1.05) == []
    topics = s.stats()["topics"]
    assert topics["/scan"]["dropped_stale"] == 1  # type: ignore[index]
    assert topics["/image"]["dropped_stale"] == 1  # type: ignore[index]
    assert s.topic_feedback("/scan").dropped >= 1  # producers see the drop


def test_after_an_outage_a_message_offered_once_the_path_worked_again_is_kept() -> None:
    """The new connection's SYN left at 1.00: a scan offered at 1.01, while the
    handshake ran, is fresh; the image offered at 0.95 was offered into the outage."""
    s = make()
    offer_every(s, "/scan", 0.1, 0.9)
    s.offer("/scan", b"/scan@1.01", 1.01, priority=1.0, no_drop=False)
    offer_every(s, "/image", 0.5, 0.5)
    s.offer("/image", b"/image@0.95", 0.95, priority=1.0, no_drop=False)
    assert s.drop_stale(1.02, after_outage=True, alive_since_s=1.0) == 1
    assert FakeLink(s).drain(1.03) == [b"/scan@1.01"]
    assert s.stats()["topics"]["/image"]["dropped_stale"] == 1  # type: ignore[index]


def test_without_an_outage_only_messages_older_than_the_period_bound_go() -> None:
    s = make()  # stale_periods 1.5
    offer_every(s, "/scan", 0.1, 1.0)  # last at 1.0: 0.1 s old at 1.1, kept
    offer_every(s, "/stopped", 0.1, 0.5)  # last at 0.5: 0.6 s old, 6 periods
    assert s.drop_stale(1.1, after_outage=False) == 1
    assert FakeLink(s).drain(1.1) == [b"/scan@1.00"]
    assert s.stats()["topics"]["/stopped"]["dropped_stale"] == 1  # type: ignore[index]


def test_no_drop_and_one_shot_topics_are_never_dropped_as_stale() -> None:
    s = make()
    s.offer("/map", b"map", 0.0, priority=1.0, no_drop=False)  # latched: offered once
    offer_every(s, "/events", 0.1, 0.3, no_drop=True)
    assert s.drop_stale(5.0, after_outage=True) == 0
    sent = FakeLink(s).drain(5.0)
    assert sorted(sent) == sorted([b"/events@0.00", b"/events@0.10", b"/events@0.20",
                                   b"/events@0.30", b"map"])


def test_a_keyframe_is_kept_unless_held_through_an_outage() -> None:
    s = make()
    for i in range(3):
        s.offer("/video", b"k%d" % i, i * 0.1, priority=1.0, no_drop=False, keyframe=True)
    assert s.drop_stale(5.0, after_outage=False) == 0  # old, but later frames need it
    assert s.drop_stale(5.0, after_outage=True) == 1


def test_after_a_dropped_video_frame_deltas_wait_for_the_next_keyframe() -> None:
    """The deltas after a dropped frame have no reference: sending them is useless."""
    s = make()
    s.offer("/video", b"key", 0.0, priority=1.0, no_drop=False, keyframe=True)
    FakeLink(s).drain(0.0)
    s.offer("/video", b"d1", 0.1, priority=1.0, no_drop=False)  # held through the outage
    assert s.drop_stale(3.0, after_outage=True) == 1
    s.offer("/video", b"d2", 3.0, priority=1.0, no_drop=False)  # refers to d1: dropped
    assert FakeLink(s).drain(3.0) == []
    s.offer("/video", b"key2", 3.1, priority=1.0, no_drop=False, keyframe=True)
    assert FakeLink(s).drain(3.1) == [b"key2"]
    s.offer("/video", b"d3", 3.2, priority=1.0, no_drop=False)
    assert FakeLink(s).drain(3.2) == [b"d3"]
    topic = s.stats()["topics"]["/video"]
    assert topic["dropped_stale"] == 1 and topic["dropped_behind_keyframe"] == 1  # type: ignore[index]


def test_the_period_is_a_moving_average_of_offer_intervals() -> None:
    s = make(period_gain=0.5)
    offer_every(s, "/a", 0.1, 0.3)  # intervals 0.1
    s.offer("/a", b"late", 0.7, priority=1.0, no_drop=False)  # one interval of 0.4
    # average 0.25: 1.5 periods = 0.375; the held message is 0.3 s old at 1.0: kept
    assert s.drop_stale(1.0, after_outage=False) == 0
    assert s.drop_stale(1.1, after_outage=False) == 1  # 0.4 s old


def test_the_next_publish_is_each_topics_last_publish_plus_whole_periods() -> None:
    """What the dialer dials just before while the link is down (``next_publish_after``);
    without publish times, the offers stand for them."""
    s = make()
    assert s.next_publish_after(0.0) == float("inf")  # no topic has a period yet
    offer_every(s, "/pose", 0.05, 1.0)  # last offer 1.00
    offer_every(s, "/scan", 0.1, 0.93, start_s=0.03)  # last offer 0.93
    assert s.next_publish_after(1.003) == pytest.approx(1.03)  # the scan's, before the pose's
    assert s.next_publish_after(1.031) == pytest.approx(1.05)  # the pose's
    # Into an outage the topics go on offering (held, replaced): far ahead it is still
    # whole periods on from the last offer, never one at or before the time asked.
    assert s.next_publish_after(3.0) == pytest.approx(3.03)
    assert s.next_publish_after(3.051) == pytest.approx(3.1)


def test_the_next_publish_comes_from_publish_times_not_offers() -> None:
    """A scan offered 2.5 ms after each publish: the next is due on the publish's phase."""
    s = make()
    for i in range(4):
        s.offer("/scan", b"s", 1.0 + 0.1 * i + 0.0025, priority=1.0, no_drop=False,
                published_s=1.0 + 0.1 * i)
    assert s.next_publish_after(1.31) == pytest.approx(1.4)
