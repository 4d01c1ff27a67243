"""Unit tests of the pure scheduler with a fake clock, a fake splitter and a fake link."""

from __future__ import annotations

import itertools

import pytest

from fleetctl.client.scheduler import (
    RateLimiter,
    Scheduler,
    SchedulerConfig,
    WindowedExtremum,
)


def fake_split(frame: bytes, *, topic: str, message_id: int, max_fragment_bytes: int,
               no_drop: bool, payload_bytes: int | None = None) -> list[bytes]:
    """Fragments tagged ``topic|id|index|`` so tests can see what went out."""
    size = max_fragment_bytes if payload_bytes is None else payload_bytes
    chunks = [frame[i:i + size] for i in range(0, len(frame), size)]
    return [f"F{topic}|{message_id}|{i}|".encode() + c for i, c in enumerate(chunks)]


def tag(frame: bytes) -> str:
    """The topic/index label of a fake fragment, or the whole small frame's text."""
    if frame.startswith(b"F/"):
        topic, _, index, _ = frame[1:].split(b"|", 3)
        return f"{topic.decode()}#{index.decode()}"
    return frame.decode(errors="replace")[:20]


def make(**kw: object) -> Scheduler:
    cfg = SchedulerConfig(**{"max_fragment_bytes": 100, **kw})  # type: ignore[arg-type]
    return Scheduler(cfg, split=fake_split)


class FakeLink:
    """Drains the scheduler like the transport does, acking on demand."""

    def __init__(self, sched: Scheduler) -> None:
        self.sched = sched
        self.sent: list[bytes] = []
        self.tokens: list[int] = []

    def drain(self, now: float, limit: int = 10_000) -> list[bytes]:
        out: list[bytes] = []
        while len(out) < limit and (frame := self.sched.next_frame(now)) is not None:
            out.append(frame)
            if self.sched.wants_ack_point(now):
                self.tokens.append(self.sched.ack_point(now))
        if self.sched.wants_ack_point(now):
            self.tokens.append(self.sched.ack_point(now))
        self.sent += out
        return out

    def ack_all(self, now: float) -> None:
        for token in self.tokens:
            self.sched.on_ack(token, now)
        self.tokens.clear()


# -- Algorithm 1 ------------------------------------------------------------------------


def test_rate_limit_keeps_a_jittery_source_at_its_rate() -> None:
    limiter = RateLimiter(tolerance=0.05)
    times = [i * 0.1 + (0.003 if i % 2 else -0.003) for i in range(50)]
    assert all(limiter.admit("/a", 10.0, t) for t in times)


def test_rate_limit_drops_a_faster_source_to_the_limit() -> None:
    limiter = RateLimiter()
    admitted = sum(limiter.admit("/a", 10.0, i * 0.01) for i in range(1000))  # 100 Hz, 10 s
    assert 99 <= admitted <= 101


def test_rate_limit_none_admits_everything_and_idle_earns_no_burst() -> None:
    limiter = RateLimiter()
    assert all(limiter.admit("/a", None, 0.0) for _ in range(10))
    assert limiter.admit("/b", 1.0, 0.0)
    assert limiter.admit("/b", 1.0, 100.0)  # long idle
    assert not limiter.admit("/b", 1.0, 100.1)  # but no burst afterwards


def test_scheduler_admit_counts_rate_limited() -> None:
    s = make()
    assert s.admit("/a", 2.0, 0.0)
    assert not s.admit("/a", 2.0, 0.1)
    assert s.stats()["topics"]["/a"]["rate_limited"] == 1  # type: ignore[index]


def test_droppable_topic_keeps_only_latest() -> None:
    s = make()
    for i in range(3):
        s.offer("/a", f"m{i}".encode(), 0.0, priority=1, no_drop=False)
    link = FakeLink(s)
    assert link.drain(1.0) == [b"m2"]
    assert s.stats()["topics"]["/a"]["dropped_replaced"] == 2  # type: ignore[index]


def test_no_drop_fifo_bounded_tail_drop_counted() -> None:
    s = make(no_drop_queue_messages=3)
    results = [s.offer("/e", f"e{i}".encode(), 0.0, priority=1, no_drop=True) for i in range(5)]
    assert results == [True, True, True, False, False]
    assert s.no_drop_overflow == 2
    assert FakeLink(s).drain(1.0) == [b"e0", b"e1", b"e2"]


def test_no_drop_bound_counts_unacked_messages_and_bytes() -> None:
    s = make(no_drop_queue_messages=2, no_drop_queue_bytes=10)
    assert s.offer("/e", b"12345", 0.0, priority=1, no_drop=True)
    FakeLink(s).drain(0.0)  # sent, not acked: still counts against the bound
    assert s.offer("/e", b"12345", 0.0, priority=1, no_drop=True)
    assert not s.offer("/e", b"1", 0.0, priority=1, no_drop=True)  # 2 messages
    s2 = make(no_drop_queue_bytes=10)
    assert s2.offer("/e", b"12345", 0.0, priority=1, no_drop=True)
    assert not s2.offer("/e", b"123456", 0.0, priority=1, no_drop=True)  # 11 bytes


# -- Algorithm 2 ------------------------------------------------------------------------


def test_no_drop_queue_goes_first() -> None:
    s = make()
    s.offer("/a", b"drop", 0.0, priority=100, no_drop=False)
    s.offer("/e", b"keep1", 0.0, priority=0, no_drop=True)
    s.offer("/e", b"keep2", 0.0, priority=0, no_drop=True)
    assert FakeLink(s).drain(1.0) == [b"keep1", b"keep2", b"drop"]


def test_fair_priority_is_descending_priority_times_wait() -> None:
    s = make()
    s.register_topic("/low", 1.0, 0.0)
    s.register_topic("/high", 10.0, 0.0)
    s.offer("/low", b"low", 0.5, priority=1.0, no_drop=False)
    s.offer("/high", b"high", 0.5, priority=10.0, no_drop=False)
    assert FakeLink(s).drain(1.0) == [b"high", b"low"]  # Robofleet's ascending bug: reverse


def test_long_wait_beats_higher_priority() -> None:
    s = make()
    s.register_topic("/low", 1.0, 0.0)  # last sent at 0
    s.register_topic("/high", 3.0, 9.0)  # last sent at 9
    s.offer("/low", b"low", 10.0, priority=1.0, no_drop=False)
    s.offer("/high", b"high", 10.0, priority=3.0, no_drop=False)
    assert FakeLink(s).drain(10.0)[0] == b"low"  # f: 1 x 10 = 10 > 3 x 1 = 3


def steps_until_sent(low_priority: float, max_steps: int) -> int | None:
    """Offer /high (priority 100) every 1 ms on an n_T = 1 link; when does /low go?"""
    s = make(fixed_window_messages=1)
    link = FakeLink(s)
    s.offer("/high", b"high", 0.0, priority=100.0, no_drop=False)
    link.drain(0.0)
    link.ack_all(0.0)
    s.offer("/low", b"low", 0.0, priority=low_priority, no_drop=False)
    for step in range(1, max_steps):
        now = step * 0.001
        s.offer("/high", b"high", now, priority=100.0, no_drop=False)
        if b"low" in link.drain(now):
            return step
        link.ack_all(now)
    return None


def test_low_priority_topic_is_not_starved() -> None:
    # f_low = 0.1 x t overtakes f_high = 100 x 1 ms after t = 1 s.
    step = steps_until_sent(0.1, 3000)
    assert step is not None and 995 <= step <= 1010


def test_priority_zero_is_background_only() -> None:
    assert steps_until_sent(0.0, 3000) is None


def test_priority_zero_goes_when_link_is_idle() -> None:
    s = make()
    s.offer("/bg", b"bg", 0.0, priority=0.0, no_drop=False)
    assert FakeLink(s).drain(1.0) == [b"bg"]


# -- in flight ----------------------------------------------------------------------------


def test_fixed_window_n_t_one_waits_for_pong() -> None:
    s = make(fixed_window_messages=1)
    link = FakeLink(s)
    s.offer("/a", b"a", 0.0, priority=1, no_drop=False)
    s.offer("/b", b"b", 0.0, priority=1, no_drop=False)
    assert len(link.drain(0.0)) == 1
    assert link.drain(0.0) == []
    assert s.in_flight_frames == 1
    link.ack_all(0.01)
    assert len(link.drain(0.01)) == 1


def test_adaptive_window_limits_bytes_in_flight() -> None:
    s = make(initial_window_bytes=250, max_fragment_bytes=100)
    link = FakeLink(s)
    s.offer("/a", b"x" * 1000, 0.0, priority=1, no_drop=False)
    sent = link.drain(0.0)
    assert sum(len(f) for f in sent) <= 250 and len(sent) == 2
    assert s.in_flight_bytes > 0 and s.next_frame(0.0) is None
    link.ack_all(0.1)
    assert s.stats(0.1)["min_rtt_ms"] == pytest.approx(100.0)
    assert s.next_frame(0.1) is not None


def rounds(s: Scheduler, rtts_s: list[float]) -> list[int]:
    """Saturate the link; each round drains the window and acks after the given RTT."""
    link = FakeLink(s)
    now, windows = 0.0, []
    for rtt in rtts_s:
        s.offer("/a", b"x" * 10_000_000, now, priority=1, no_drop=True)
        link.drain(now)
        now += rtt
        link.ack_all(now)
        windows.append(s.window_bytes())
    return windows


def test_window_doubles_per_rtt_while_the_queue_is_empty() -> None:
    # The delay-based window alone (the rate cap lags a doubling window by design).
    s = make(max_fragment_bytes=1000, initial_window_bytes=4000, max_window_bytes=10**9,
             rate_cap_gain=None)
    windows = rounds(s, [0.001] * 6)
    assert all(b >= 1.7 * a for a, b in itertools.pairwise(windows))
    assert windows[-1] >= 2**5 * 4000 * 0.9


def test_window_shrinks_to_one_fragment_when_the_queue_grows() -> None:
    s = make(max_fragment_bytes=1000, initial_window_bytes=64_000)
    windows = rounds(s, [0.001] + [0.05] * 8)  # RTT 50 ms over a 1 ms min: queueing
    assert windows[0] > 64_000
    assert windows[-1] == s.fragment_bytes() == 1000


def test_window_is_capped_at_link_rate_times_min_rtt_plus_target() -> None:
    # A token bucket's burst makes acks look instant; the cap from the busy-time link rate
    # keeps the window at one min RTT plus the target queue of the real rate.
    s = make(max_fragment_bytes=1000, initial_window_bytes=64_000, target_queue_delay_s=0.004)
    rounds(s, [0.001])
    assert s.window_bytes() > 64_000
    s._link_rate.clear()
    s._link_rate.add(0.0, 750_000.0)  # 6 Mbit/s
    s._update_limits()
    assert s.window_bytes() == int(750_000 * (0.001 + 0.004))
    uncapped = make(max_fragment_bytes=1000, initial_window_bytes=64_000, rate_cap_gain=None)
    rounds(uncapped, [0.001])
    uncapped._link_rate.add(0.0, 750_000.0)
    uncapped._update_limits()
    assert uncapped.window_bytes() > 64_000


def test_window_cap_never_goes_below_one_fragment() -> None:
    s = make(max_fragment_bytes=4096, min_fragment_bytes=4096, initial_window_bytes=64_000)
    rounds(s, [0.001])
    s._link_rate.clear()
    s._link_rate.add(0.0, 1000.0)  # 1 KB/s: the cap would be 5 bytes
    s._update_limits()
    assert s.window_bytes() == s.fragment_bytes() == 4096


def test_window_holds_near_the_target_delay() -> None:
    s = make(max_fragment_bytes=1000, initial_window_bytes=20_000, target_queue_delay_s=0.004)
    before = rounds(s, [0.001, 0.005])  # queueing delay 4 ms: exactly on target
    assert before[1] == before[0]


def test_fragment_size_follows_link_rate() -> None:
    s = make(max_fragment_bytes=65536, min_fragment_bytes=1024, initial_fragment_bytes=16384,
             fragment_time_s=0.003)
    assert s.fragment_bytes() == 16384  # no rate sample yet
    s._link_rate.add(0.0, 750_000.0)  # 6 Mbit/s: 2250 B per 3 ms -> 2048
    s._update_limits()
    assert s.fragment_bytes() == 2048
    s._link_rate.add(0.0, 10e9)
    s._update_limits()
    assert s.fragment_bytes() == 65536  # capped
    slow = make(max_fragment_bytes=65536, min_fragment_bytes=1024)
    slow._link_rate.add(0.0, 1000.0)
    slow._update_limits()
    assert slow.fragment_bytes() == 1024  # floored


def test_rates_rescaled_when_deflate_stops_shrink_fragments_and_window() -> None:
    """Rates measured while every fragment was deflated (a compressible cloud looked 20x
    faster in frame bytes) count in raw bytes again: fragments and window shrink at once,
    not after the rate hold (fleetctl.client.slowdeflate)."""
    s = make(max_fragment_bytes=65536, min_fragment_bytes=1024, fragment_time_s=0.003,
             target_queue_delay_s=0.004)
    s._min_rtt.add(0.0, 0.001)
    s._busy_rate.add(0.0, 100_000, 0.01)
    s._link_rate.add(0.0, 15_000_000.0)  # 750 kB/s on the wire, deflated to 1/20
    s._update_limits()
    assert s.fragment_bytes() == 32768
    s.rescale_rates(1 / 20)
    assert s.link_rate_Bps == pytest.approx(750_000.0)
    assert s.fragment_bytes() == 2048
    assert s.window_bytes() <= 750_000 * 0.005 + 1
    assert s._busy_rate.rate() == pytest.approx(500_000.0)
    for factor in (0.0, 1.0, 3.0):  # nothing to rescale, or not a shrink: unchanged
        s.rescale_rates(factor)
        assert s.link_rate_Bps == pytest.approx(750_000.0)


def test_a_sizer_set_by_the_link_gives_each_topic_s_fragments_their_share() -> None:
    """While the link deflates everything it sizes each topic's fragments
    (fleetctl.client.segmentfill): a message split then carries its topic's share; a
    topic the sizer has no share for, or no sizer, gets fragment_bytes()."""
    s = make(max_fragment_bytes=65536, min_fragment_bytes=1024, fragment_time_s=0.003,
             initial_window_bytes=10**6)
    s._link_rate.add(0.0, 400_000.0)
    s._update_limits()
    assert s.fragment_bytes() == 1024
    s.fragment_sizer = {"/image": 1400, "/cloud": 2300}.get
    s.offer("/image", b"z" * 7000, 0.0, priority=1.0, no_drop=False)
    assert [f.count(b"z") for f in FakeLink(s).drain(0.0)] == [1400] * 5
    s.offer("/cloud", b"q" * 5000, 0.1, priority=1.0, no_drop=False)
    assert [f.count(b"q") for f in FakeLink(s).drain(0.1)] == [2300, 2300, 400]
    s.offer("/misc", b"o" * 3000, 0.2, priority=1.0, no_drop=False)
    assert [f.count(b"o") for f in FakeLink(s).drain(0.2)] == [1024, 1024, 952]
    s.fragment_sizer = None
    s.offer("/image", b"j" * 3000, 0.3, priority=1.0, no_drop=False)
    assert [f.count(b"j") for f in FakeLink(s).drain(0.3)] == [1024, 1024, 952]


def test_frame_within_the_link_time_budget_goes_whole() -> None:
    # 3 ms at 400 kB/s is 1200 B: fragments of 1024 B, but a 1100 B frame (just over
    # the power of two, like a cloud of 1 MiB of points) is not split into 1024 + 76.
    s = make(max_fragment_bytes=65536, min_fragment_bytes=256, fragment_time_s=0.003,
             whole_frame_budgets=1.0, initial_window_bytes=10**6)
    s._link_rate.add(0.0, 400_000.0)
    s._update_limits()
    assert (s.fragment_bytes(), s.whole_frame_bytes()) == (1024, 1200)
    s.offer("/cloud", b"c" * 1100, 0.0, priority=1.0, no_drop=False)
    assert FakeLink(s).drain(0.0) == [b"c" * 1100]
    s.offer("/cloud", b"d" * 1300, 0.1, priority=1.0, no_drop=False)  # over the budget
    assert [tag(f) for f in FakeLink(s).drain(0.1)] == ["/cloud#0", "/cloud#1"]


def test_a_frame_under_two_budgets_goes_whole_and_a_longer_one_in_budget_fragments() -> None:
    # 3 ms at 1.5 MB/s (12 Mbit/s) is 4,500 B: fragments of 4 KiB. A 6 KB scan is under
    # two budgets: split, it would go as 4 KiB + 1.9 KB, two messages through every hop
    # for an urgent wait cut by less than half. A 64 KB frame still goes in 4 KiB pieces.
    s = make(max_fragment_bytes=65536, min_fragment_bytes=1024, fragment_time_s=0.003,
             initial_window_bytes=10**6)
    s._link_rate.add(0.0, 1_500_000.0)
    s._update_limits()
    assert (s.fragment_bytes(), s.whole_frame_bytes()) == (4096, 9000)
    s.offer("/scan", b"s" * 6000, 0.0, priority=1.0, no_drop=False)
    assert FakeLink(s).drain(0.0) == [b"s" * 6000]
    s.offer("/cloud", b"c" * 9001, 0.1, priority=1.0, no_drop=False)
    assert [tag(f) for f in FakeLink(s).drain(0.1)] == ["/cloud#0", "/cloud#1", "/cloud#2"]


def test_before_the_first_rate_sample_a_frame_under_two_initial_fragments_goes_whole() -> None:
    # A new connection (after an outage) has no rate yet: the 6 KB scan still goes whole.
    s = make(max_fragment_bytes=65536, initial_fragment_bytes=4096, initial_window_bytes=10**6)
    assert (s.fragment_bytes(), s.whole_frame_bytes()) == (4096, 8192)
    s.offer("/scan", b"s" * 6000, 0.0, priority=1.0, no_drop=False)
    assert FakeLink(s).drain(0.0) == [b"s" * 6000]
    s.offer("/cloud", b"c" * 8200, 0.1, priority=1.0, no_drop=False)
    assert [tag(f) for f in FakeLink(s).drain(0.1)] == ["/cloud#0", "/cloud#1", "/cloud#2"]


def test_a_small_message_s_round_trip_is_not_taken_for_the_link_rate() -> None:
    # A new connection's first ack is a 256 B pose after 1 ms: 256 kB/s, a twentieth of the
    # link. It must not shrink the fragments below the initial ones; acks of a window in
    # use (fragments waiting behind the ping) do count, from 4 KiB acked on.
    s = make(max_fragment_bytes=65536, min_fragment_bytes=1024, initial_fragment_bytes=4096,
             initial_window_bytes=16_000)  # an ack point after every 4 KB
    link = FakeLink(s)
    s.offer("/pose", b"p" * 256, 0.0, priority=2.0, no_drop=False)
    link.drain(0.0)
    link.ack_all(0.001)
    assert s.stats()["link_rate_Bps"] == 0.0
    assert (s.fragment_bytes(), s.whole_frame_bytes()) == (4096, 8192)
    s.offer("/cloud", b"c" * 40_000, 0.1, priority=1.0, no_drop=False)
    out = link.drain(0.1, limit=3)  # three 4 KiB fragments, each with its ack point
    assert len(out) == 3 and s.has_sendable()
    link.ack_all(0.103)  # 12 KiB over 3 ms of busy time, more waiting
    # One measurement (the three pongs read together), the connection's first: held.
    assert s.stats()["link_rate_Bps"] == 0.0
    link.drain(0.103, limit=3)
    link.ack_all(0.106)  # the next flight (acked in part) confirms it: both count
    cloud_acked = s._acked_bytes_total - 256
    assert cloud_acked > 3 * 4096
    assert s.stats()["link_rate_Bps"] == pytest.approx(cloud_acked / 0.006, rel=0.05)


def test_the_whole_frame_bound_never_exceeds_max_fragment_bytes() -> None:
    s = make(max_fragment_bytes=4096, min_fragment_bytes=1024, fragment_time_s=0.003)
    s._link_rate.add(0.0, 1_000_000.0)  # a 3,000 B budget: twice is over the cap
    s._update_limits()
    assert (s.fragment_bytes(), s.whole_frame_bytes()) == (2048, 4096)


def test_in_flight_message_bound() -> None:
    s = make(max_window_messages=3, initial_window_bytes=10**6)
    for i in range(5):
        s.offer(f"/t{i}", b"m", 0.0, priority=1, no_drop=False)
    assert len(FakeLink(s).drain(0.0)) == 3


def test_ack_covers_only_frames_before_the_ping() -> None:
    s = make(initial_window_bytes=10**6, ack_every_window_fraction=1.0)
    s.offer("/a", b"a", 0.0, priority=1, no_drop=False)
    assert s.next_frame(0.0) == b"a"
    token = s.ack_point(0.0)
    s.offer("/b", b"bb", 0.0, priority=1, no_drop=False)
    assert s.next_frame(0.0) == b"bb"
    assert s.on_ack(token, 0.01)
    assert s.in_flight_bytes == 2
    assert not s.on_ack(token, 0.02)  # already acked: unknown now
    assert not s.on_ack(999, 0.02)


def test_a_later_pong_acknowledges_earlier_pings() -> None:
    s = make(initial_window_bytes=10**6)
    tokens = []
    for i in range(3):
        s.offer("/a", b"abc", float(i), priority=1, no_drop=False)
        s.next_frame(float(i))
        tokens.append(s.ack_point(float(i)))
    s.on_ack(tokens[-1], 3.0)
    assert s.in_flight_bytes == 0
    assert s.stats()["topics"]["/a"]["acked"] == 3  # type: ignore[index]


def test_wants_ack_point_after_a_window_fraction_or_when_idle() -> None:
    s = make(initial_window_bytes=1000, ack_every_window_fraction=0.5)
    assert not s.wants_ack_point(0.0)
    s.offer("/a", b"x" * 300, 0.0, priority=1, no_drop=False)
    s.offer("/b", b"y" * 300, 0.0, priority=1, no_drop=False)
    s.next_frame(0.0)
    assert not s.wants_ack_point(0.0)  # 100 B sent, more queued, under 500 B
    while s.next_frame(0.0) is not None:
        pass
    assert s.wants_ack_point(0.0)
    s.ack_point(0.0)
    assert not s.wants_ack_point(0.0)


# -- fragments ----------------------------------------------------------------------------


def test_large_message_is_split_and_small_one_is_not() -> None:
    s = make()
    s.offer("/big", b"x" * 250, 0.0, priority=1, no_drop=False)
    sent = FakeLink(s).drain(1.0)
    assert [tag(f) for f in sent] == ["/big#0", "/big#1", "/big#2"]
    s.offer("/small", b"y" * 100, 1.0, priority=1, no_drop=False)
    assert FakeLink(s).drain(2.0) == [b"y" * 100]


def test_fragments_off_sends_whole_frames() -> None:
    s = make(fragments=False)
    s.offer("/big", b"x" * 250, 0.0, priority=1, no_drop=False)
    assert FakeLink(s).drain(1.0) == [b"x" * 250]


def test_urgent_message_waits_at_most_one_fragment_of_a_cloud() -> None:
    s = make(max_fragment_bytes=16_000, initial_fragment_bytes=16_000, initial_window_bytes=10**9)
    s.register_topic("/urgent", 10.0, 0.0)
    s.offer("/cloud", b"c" * 1_000_000, 0.0, priority=1.0, no_drop=False)
    link = FakeLink(s)
    assert len(link.drain(0.0, limit=2)) == 2
    s.offer("/urgent", b"u" * 1000, 0.02, priority=10.0, no_drop=False)
    assert link.drain(0.02, limit=1) == [b"u" * 1000]
    rest = link.drain(0.03)
    assert tag(rest[0]) == "/cloud#2" and len(rest) == 63 - 2


def test_fragments_of_equal_topics_interleave() -> None:
    s = make()
    s.register_topic("/a", 1.0, 0.0)
    s.register_topic("/b", 1.0, 0.0)
    s.offer("/a", b"a" * 300, 0.0, priority=1, no_drop=False)
    s.offer("/b", b"b" * 300, 0.0, priority=1, no_drop=False)
    link = FakeLink(s)
    order = []
    for i in range(1, 7):
        order += [tag(f) for f in link.drain(i * 0.01, limit=1)]
    assert order == ["/a#0", "/b#0", "/a#1", "/b#1", "/a#2", "/b#2"]


def test_newer_data_supersedes_a_message_being_sent() -> None:
    """When what is left of the message being sent is more than the newer message."""
    s = make()
    link = FakeLink(s)
    s.offer("/cloud", b"1" * 600, 0.0, priority=1, no_drop=False)
    assert len(link.drain(0.0, limit=1)) == 1
    s.offer("/cloud", b"2" * 300, 0.1, priority=1, no_drop=False)  # 500 B left of 1
    rest = link.drain(0.1)
    assert all(f.endswith(b"2" * 100) for f in rest) and len(rest) == 3
    st = s.stats()["topics"]["/cloud"]  # type: ignore[index]
    assert st["dropped_superseded"] == 1 and st["sent"] == 1


def test_a_message_with_less_left_than_the_newer_one_completes_first() -> None:
    """Superseding it would throw away the link time spent on it and bring the newer one
    no sooner than finishing it brings data."""
    s = make()
    link = FakeLink(s)
    s.offer("/cloud", b"1" * 300, 0.0, priority=1, no_drop=False)
    link.drain(0.0, limit=1)
    s.offer("/cloud", b"2" * 300, 0.1, priority=1, no_drop=False)  # ~220 B left of 1
    assert [f[-1:] for f in link.drain(0.1)] == [b"1", b"1", b"2", b"2", b"2"]
    st = s.stats()["topics"]["/cloud"]  # type: ignore[index]
    assert st["dropped_superseded"] == 0 and st["sent"] == 2


def test_a_link_slower_than_the_topic_is_not_spent_on_abandoned_messages() -> None:
    """A cloud at 5 Hz on a link that needs 0.3 s per cloud (the e2e multi-consumer run
    with a starved tunnel): before, every other cloud was superseded mostly sent, and
    the link delivered 1 cloud per 0.5 s of its time instead of 1 per 0.3 s."""
    s = make()
    link = FakeLink(s)
    frame_per_step, step_s, period_s = 1, 0.01, 0.2  # 100 B per 10 ms: 1,000 B in 0.1 s
    size = 3000  # 0.3 s of link time
    sent_bytes = 0
    for n in range(300):  # 3 s
        now = n * step_s
        if n % round(period_s / step_s) == 0:
            s.offer("/cloud", bytes([n % 250]) * size, now, priority=1, no_drop=False)
        sent_bytes += sum(len(f) for f in link.drain(now, limit=frame_per_step))
        link.ack_all(now)
    st = s.stats()["topics"]["/cloud"]  # type: ignore[index]
    assert st["dropped_superseded"] == 0
    assert st["sent"] >= 9  # 3 s of link time / 0.3 s, less the last one's rest
    assert st["sent"] * size / sent_bytes > 0.85  # the rest is fragment headers


def test_supersede_streak_guard_lets_a_message_complete() -> None:
    s = make()
    link = FakeLink(s)
    s.offer("/c", b"1" * 900, 0.0, priority=1, no_drop=False)
    link.drain(0.0, limit=1)
    s.offer("/c", b"2" * 600, 0.1, priority=1, no_drop=False)  # supersedes 1
    link.drain(0.1, limit=1)
    s.offer("/c", b"3" * 100, 0.2, priority=1, no_drop=False)  # 2 is protected
    rest = link.drain(0.2)
    assert [f[-1:] for f in rest] == [b"2"] * 5 + [b"3"]
    st = s.stats()["topics"]["/c"]  # type: ignore[index]
    assert st["dropped_superseded"] == 1 and st["sent"] == 2


def test_window_full_does_not_start_a_pending_message() -> None:
    s = make(fixed_window_messages=1)
    link = FakeLink(s)
    s.offer("/a", b"a", 0.0, priority=1, no_drop=False)
    link.drain(0.0)
    s.offer("/c", b"1" * 300, 0.0, priority=1, no_drop=False)
    assert link.drain(0.0) == []
    s.offer("/c", b"2" * 300, 0.0, priority=1, no_drop=False)  # replaces, not supersedes
    st = s.stats()["topics"]["/c"]  # type: ignore[index]
    assert st["dropped_replaced"] == 1 and st["dropped_superseded"] == 0


# -- reconnect ----------------------------------------------------------------------------


def test_disconnect_requeues_unacked_no_drop_in_order_and_drops_partial_droppable() -> None:
    s = make(fixed_window_messages=100, ack_every_window_fraction=10.0)
    link = FakeLink(s)
    s.offer("/e", b"e0", 0.0, priority=1, no_drop=True)
    link.drain(0.0)
    link.ack_all(0.01)  # e0 delivered
    for i in (1, 2):
        s.offer("/e", f"e{i}".encode(), 0.02, priority=1, no_drop=True)
    s.offer("/e", b"E" * 250, 0.02, priority=1, no_drop=True)  # 3 fragments
    s.offer("/e", b"e4", 0.02, priority=1, no_drop=True)
    s.offer("/cloud", b"c" * 300, 0.02, priority=1, no_drop=False)
    assert len(link.drain(0.02, limit=4)) == 4  # e1, e2, E#0, E#1 (unacked)
    link.tokens.clear()  # those pongs never come
    s.on_disconnect(0.5)
    assert s.in_flight_bytes == 0
    s.offer("/cloud", b"d" * 50, 0.6, priority=1, no_drop=False)
    resent = link.drain(1.0)
    assert [tag(f) for f in resent[:2]] == ["e1", "e2"]
    assert [tag(f) for f in resent[2:5]] == ["/e#0", "/e#1", "/e#2"]
    assert resent[5:] == [b"e4", b"d" * 50]
    st = s.stats()["topics"]
    assert st["/e"]["requeued"] == 2  # type: ignore[index]
    assert st["/cloud"]["dropped_replaced"] == 1  # type: ignore[index]


def test_disconnect_drops_a_partly_sent_droppable_message() -> None:
    s = make()
    link = FakeLink(s)
    s.offer("/cloud", b"c" * 300, 0.0, priority=1, no_drop=False)
    link.drain(0.0, limit=1)
    s.on_disconnect(0.1)
    assert link.drain(0.2) == []
    assert s.stats()["topics"]["/cloud"]["dropped_disconnect"] == 1  # type: ignore[index]


def test_pong_from_before_a_disconnect_is_ignored() -> None:
    s = make()
    s.offer("/a", b"a", 0.0, priority=1, no_drop=True)
    s.next_frame(0.0)
    token = s.ack_point(0.0)
    s.on_disconnect(0.1)
    assert not s.on_ack(token, 0.2)
    assert FakeLink(s).drain(0.3) == [b"a"]


# -- helpers --------------------------------------------------------------------------------


def test_windowed_extremum() -> None:
    mx = WindowedExtremum(1.0, keep_max=True)
    assert mx.value(0.0, -1.0) == -1.0
    for t, v in [(0.0, 5.0), (0.5, 3.0), (0.9, 4.0)]:
        mx.add(t, v)
    assert mx.value(0.9, 0.0) == 5.0
    assert mx.value(1.2, 0.0) == 4.0  # 5.0 expired
    mn = WindowedExtremum(1.0, keep_max=False)
    for t, v in [(0.0, 5.0), (0.5, 3.0), (0.9, 4.0)]:
        mn.add(t, v)
    assert mn.value(1.6, 0.0) == 4.0
    mn.clear()
    assert mn.value(None, 7.0) == 7.0


def test_busy_rate_averages_bursts_over_time() -> None:
    from fleetctl.client.scheduler import BusyRate

    rate = BusyRate(0.5)
    assert rate.rate() == 0.0
    rate.add(0.0, 4000, 0.0002)  # a token-bucket burst: 20 MB/s for 0.2 ms
    for i in range(1, 50):
        rate.add(i * 0.0053, 4000, 0.0053)  # then 750 kB/s
    assert 700_000 < rate.rate() < 800_000
    rate.add(10.0, 1000, 0.001)  # everything older than 0.5 s expires
    assert rate.rate() == pytest.approx(1_000_000)
    rate.clear()
    assert rate.rate() == 0.0


def fanout_link() -> tuple[Scheduler, FakeLink]:
    """A scheduler on the e2e peer-fanout link as the robot measured it (1.17 MB/s, 1 ms
    min RTT, 4 ms target: a 5.85 KB rate cap, 2 KiB fragments, 7 KB whole frames)."""
    s = make(max_fragment_bytes=4 * 1024 * 1024, target_queue_delay_s=0.004)
    s._min_rtt.add(0.0, 0.001)
    s._link_rate.add(0.0, 1_170_000.0)
    s._update_limits()
    return s, FakeLink(s)


def test_a_frame_sent_whole_does_not_wait_behind_a_small_one_in_flight() -> None:
    # The e2e peer-fanout link as the robot measured it: 1.17 MB/s, 1 ms min RTT, so the
    # window (the rate cap) is 1.17 MB/s x 5 ms = 5.85 KB, under the 7 KB a frame may be
    # to go whole (two 3 ms budgets). A 6.4 KB scan after a pose still in flight goes at
    # once, whole.
    s, link = fanout_link()
    assert s.window_bytes() < 256 + 6_400 <= s.whole_frame_bytes()
    s.offer("/pose", b"p" * 256, 1.0, priority=2, no_drop=False)
    assert link.drain(1.0) == [b"p" * 256]
    s.offer("/scan", b"s" * 6_400, 1.0, priority=1, no_drop=False)
    assert link.drain(1.0) == [b"s" * 6_400]
    assert s.in_flight_bytes == 256 + 6_400


def test_fragments_keep_the_window_that_whole_frames_may_exceed() -> None:
    # Same link: a 20 KB cloud goes in 2 KiB fragments, and they stop at the 5.85 KB
    # window, not at the whole-frame limit: an urgent message waits behind at most that.
    s, link = fanout_link()
    assert s.fragment_bytes() == 2048
    s.offer("/pose", b"p" * 256, 1.0, priority=2, no_drop=False)
    link.drain(1.0)
    s.offer("/cloud", b"c" * 20_000, 1.0, priority=1, no_drop=False)
    assert [tag(f) for f in link.drain(1.0)] == ["/cloud#0", "/cloud#1"]
    assert s.in_flight_bytes <= s.window_bytes() < s.whole_frame_bytes()


def peer_load(s: Scheduler, seconds: float) -> list[int]:
    """The e2e ``peer`` load as a new connection's scheduler sees it on a fast link: a
    256 B pose every 50 ms acked after 2.5 ms, a 6 KB scan every 100 ms whose flights are
    acked 1.6 ms after they went. Returns how many frames each scan took."""
    link, frames = FakeLink(s), []
    for i in range(int(seconds * 10)):
        now = i * 0.1
        for pose_at in (now + 0.02, now + 0.07):
            s.offer("/pose", b"p" * 256, pose_at, priority=2.0, no_drop=False)
            link.drain(pose_at)
            link.ack_all(pose_at + 0.0025)
        now += 0.08
        s.offer("/scan", bytes([65 + i % 26]) * 6000, now, priority=1.0, no_drop=False)
        sent = 0
        while s.has_sendable():
            sent += len(link.drain(now))
            now += 0.0016
            link.ack_all(now)
        frames.append(sent)
    return frames


def test_a_light_load_s_small_round_trips_do_not_set_the_link_rate() -> None:
    # Counted, the poses' round trips read 0.1 MB/s and split the scan into fragments.
    s = make(max_fragment_bytes=4 * 1024 * 1024, min_fragment_bytes=1024,
             fragment_time_s=0.003, target_queue_delay_s=0.004)
    frames = peer_load(s, 3.0)
    assert frames == [1] * 30, frames  # every scan whole
    # The whole scans' acks are the link's rate: 6 KB in 1.6 ms.
    assert s.stats()["link_rate_Bps"] == pytest.approx(6000 / 0.0016, rel=0.05)


def test_a_whole_message_s_round_trip_on_a_slow_link_still_sizes_the_fragments() -> None:
    # 1 Mbit/s: a lone 6 KB scan takes 48 ms; app-limited, yet the link's own time.
    s = make(max_fragment_bytes=65536, min_fragment_bytes=1024, initial_window_bytes=10**6)
    link = FakeLink(s)
    s.offer("/scan", b"s" * 6000, 0.0, priority=1.0, no_drop=False)
    assert link.drain(0.0) == [b"s" * 6000]
    link.ack_all(0.048)
    assert s.fragment_bytes() == 4096  # a connection's first sample waits for the next
    s.offer("/scan", b"t" * 6000, 0.1, priority=1.0, no_drop=False)
    assert link.drain(0.1) == [b"t" * 6000]
    link.ack_all(0.149)  # as slow: it confirms the first, and both count
    assert s.stats()["link_rate_Bps"] == pytest.approx(12000 / 0.097, rel=0.01)
    assert s.fragment_bytes() == 1024


def scans_acked_after(s: Scheduler, link: FakeLink, start_s: float,
                      *round_trips: float) -> None:
    """From *start_s*, a 6 KB scan every 0.1 s, each acknowledged after its round trip."""
    for i, rtt in enumerate(round_trips):
        now = start_s + i * 0.1
        s.offer("/scan", bytes([65 + i]) * 6000, now, priority=1.0, no_drop=False)
        assert link.drain(now) == [bytes([65 + i]) * 6000]
        link.ack_all(now + rtt)


def test_a_new_connection_s_cold_first_sample_does_not_size_the_fragments() -> None:
    # The e2e peer load after a reconnect on its 4 Mbit/s link: the first scan took
    # 13.8 ms through cold paths, the next 4 ms. Counted, the first read 0.43 MB/s and
    # cut the next scans into 1 KiB fragments; held, the faster next one drops it.
    s = make(max_fragment_bytes=65536, min_fragment_bytes=1024, initial_window_bytes=10**6)
    link = FakeLink(s)
    scans_acked_after(s, link, 1.0, 0.0138)
    assert (s.link_rate_Bps, s.fragment_bytes(), s.whole_frame_bytes()) == (0.0, 4096, 8192)
    scans_acked_after(s, link, 1.1, 0.004)
    assert s.link_rate_Bps == pytest.approx(6000 / 0.004)
    assert s.whole_frame_bytes() >= 6000  # the scans go whole
    # After a disconnect the next connection's first sample is held again.
    s.on_disconnect(2.0)
    scans_acked_after(s, link, 2.1, 0.05)
    assert s.link_rate_Bps == 0.0
