"""TF republishing semantics: per-pair deltas, the overall rate bound, static accumulation."""

from __future__ import annotations

import itertools
import math
import random
from types import SimpleNamespace
from typing import Any

import pytest

from fleetctl.client.config import TfSpec
from fleetctl.client.tfthrottle import (
    MAX_PAIRS,
    SNAPSHOT_PERIOD_S,
    StaticTf,
    TfEmission,
    TfThrottle,
    pair_of,
    pose_of,
    rotation_rad,
    translation_m,
)


def tf(parent: str, child: str, x: float = 0.0, y: float = 0.0, z: float = 0.0,
       yaw: float = 0.0, stamp: int = 0) -> Any:
    """A TransformStamped-like object (rotation about z by *yaw* rad)."""
    return SimpleNamespace(
        header=SimpleNamespace(frame_id=parent, stamp=SimpleNamespace(sec=stamp, nanosec=0)),
        child_frame_id=child,
        transform=SimpleNamespace(
            translation=SimpleNamespace(x=x, y=y, z=z),
            rotation=SimpleNamespace(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))))


def names(out: TfEmission | list[Any] | None) -> list[str]:
    """Child frames of a throttle's emission or of StaticTf's message."""
    transforms = out.transforms if isinstance(out, TfEmission) else out or []
    return [t.child_frame_id for t in transforms]


def deltas_only(spec: TfSpec) -> TfThrottle:
    """A throttle whose only snapshot is its first message: the delta logic alone."""
    return TfThrottle(spec, snapshot_period_s=math.inf)


def test_first_sight_of_every_pair_is_sent_in_one_message() -> None:
    throttle = TfThrottle(TfSpec())
    throttle.offer([tf("odom", "base_link"), tf("base_link", "laser", x=0.2)])
    # One message, pairs in (parent, child) order.
    first = throttle.poll(0.0)
    assert names(first) == ["laser", "base_link"]
    assert first is not None and first.snapshot  # the first message is the whole tree
    assert throttle.poll(0.0) is None  # nothing new
    assert throttle.stats.messages_out == 1 and throttle.stats.transforms_out == 2


def test_only_pairs_that_moved_beyond_a_delta_are_sent() -> None:
    spec = TfSpec(translation_delta_m=0.01, rotation_delta_rad=0.02, max_rate_hz=10.0)
    throttle = deltas_only(spec)
    throttle.offer([tf("odom", "base_link"), tf("base_link", "wheel")])
    throttle.poll(0.0)
    # 9 mm and 0.019 rad: under both deltas; the wheel turns 0.03 rad: over.
    throttle.offer([tf("odom", "base_link", x=0.009, yaw=0.019),
                    tf("base_link", "wheel", yaw=0.03)])
    assert names(throttle.poll(1.0)) == ["wheel"]
    # Small steps add up: compared with what was sent, not with the previous message.
    throttle.offer([tf("odom", "base_link", x=0.011)])
    assert names(throttle.poll(2.0)) == ["base_link"]


def test_a_pair_that_moved_and_came_back_within_the_period_is_not_sent() -> None:
    throttle = TfThrottle(TfSpec(max_rate_hz=1.0))
    throttle.offer([tf("odom", "base_link")])
    throttle.poll(0.0)
    throttle.offer([tf("odom", "base_link", x=0.5)])
    assert throttle.poll(0.5) is None  # too soon
    throttle.offer([tf("odom", "base_link", x=0.001)])
    assert throttle.poll(1.0) is None


def test_rate_bound_holds_and_the_latest_transform_goes_out() -> None:
    throttle = TfThrottle(TfSpec(max_rate_hz=10.0))
    sent_at: list[float] = []
    last: list[Any] = []
    # /tf at 100 Hz, every message moving 5 cm: the rate bound decides alone.
    for i in range(300):
        now = i * 0.01
        throttle.offer([tf("odom", "base_link", x=0.05 * i)])
        out = throttle.poll(now)
        if out is not None:
            sent_at.append(now)
            last = out.transforms
    gaps = [b - a for a, b in itertools.pairwise(sent_at)]
    assert min(gaps) >= 0.1 - 1e-9
    assert 28 <= len(sent_at) <= 30
    assert last[0].transform.translation.x == pytest.approx(0.05 * (sent_at[-1] / 0.01))


def test_receiver_stays_within_the_deltas_after_every_emission() -> None:
    spec = TfSpec(translation_delta_m=0.02, rotation_delta_rad=0.05, max_rate_hz=10.0)
    throttle = TfThrottle(spec)
    rng = random.Random(7)
    frames = [f"link{i}" for i in range(20)]
    pose = {f: [0.0, 0.0] for f in frames}  # x, yaw
    received: dict[str, Any] = {}
    emissions = 0
    for step in range(2000):
        now = step * 0.005  # /tf at 200 Hz
        moved = rng.sample(frames, 5)
        for f in moved:
            pose[f][0] += rng.uniform(-0.004, 0.004)
            pose[f][1] += rng.uniform(-0.01, 0.01)
        throttle.offer([tf("base", f, x=pose[f][0], yaw=pose[f][1]) for f in moved])
        out = throttle.poll(now)
        if out is None:
            continue
        emissions += 1
        for t in out.transforms:
            received[t.child_frame_id] = pose_of(t)
        # Right after an emission, what the receiver holds is within the deltas of the
        # newest transform of every pair.
        assert set(received) == {f for f in frames if throttle.latest_pose(("base", f))}
        for f in received:
            latest = throttle.latest_pose(("base", f))
            assert latest is not None
            assert translation_m(received[f], latest) <= spec.translation_delta_m
            assert rotation_rad(received[f], latest) <= spec.rotation_delta_rad
    assert emissions > 50
    assert throttle.stats.transforms_out < throttle.stats.transforms_in / 4


def test_rotation_angle_is_the_full_angle_and_sign_blind() -> None:
    a = pose_of(tf("a", "b", yaw=0.0))
    b = pose_of(tf("a", "b", yaw=0.3))
    assert rotation_rad(a, b) == pytest.approx(0.3)
    negated = tf("a", "b", yaw=0.3)
    q = negated.transform.rotation
    q.z, q.w = -q.z, -q.w
    assert rotation_rad(b, pose_of(negated)) == pytest.approx(0.0, abs=1e-6)


def test_leading_slash_is_the_same_frame() -> None:
    assert pair_of(tf("/odom", "/base_link")) == ("odom", "base_link")
    throttle = TfThrottle(TfSpec())
    throttle.offer([tf("/odom", "base_link")])
    throttle.poll(0.0)
    throttle.offer([tf("odom", "/base_link")])
    assert throttle.poll(1.0) is None and len(throttle) == 1


@pytest.mark.parametrize("bad", [
    tf("a", "b", x=math.nan), tf("a", "b", y=math.inf), SimpleNamespace(child_frame_id="x")])
def test_invalid_transforms_are_counted_not_raised(bad: Any) -> None:
    throttle = TfThrottle(TfSpec())
    zero = tf("a", "c")
    zero.transform.rotation.w = 0.0
    throttle.offer([bad, zero, tf("a", "ok")])
    assert names(throttle.poll(0.0)) == ["ok"]
    assert throttle.stats.invalid == 2


def test_pair_table_is_bounded() -> None:
    throttle = TfThrottle(TfSpec())
    throttle.offer([tf("world", f"f{i}") for i in range(MAX_PAIRS + 10)])
    assert len(throttle) == MAX_PAIRS and throttle.stats.pairs_over_limit == 10
    out = throttle.poll(0.0)
    assert out is not None and len(out.transforms) == MAX_PAIRS


def test_static_transforms_accumulate_and_are_resent_whole() -> None:
    static = StaticTf()
    assert names(static.offer([tf("base_link", "laser", x=0.2)])) == ["laser"]
    # Another broadcaster's message: everything known goes out again.
    assert names(static.offer([tf("base_link", "camera", z=0.5)])) == ["camera", "laser"]
    # The same set again (a re-sent latched sample): nothing to send.
    assert static.offer([tf("base_link", "laser", x=0.2)]) is None
    # A changed static pair: the whole set, with the new value.
    out = static.offer([tf("base_link", "laser", x=0.25)])
    assert names(out) == ["camera", "laser"]
    assert out is not None and out[1].transform.translation.x == 0.25
    assert static.stats.static_out == 3 and len(static) == 2


def test_a_late_viewer_gets_pairs_that_stopped_moving_from_a_latched_snapshot() -> None:
    # A localizer's map -> odom never moves; odom -> base_link moves for 5 s, then parks.
    throttle = TfThrottle(TfSpec(max_rate_hz=10.0))
    sent: list[tuple[float, TfEmission]] = []
    for step in range(200):  # /tf at 20 Hz for 10 s
        now = step * 0.05
        x = min(now, 5.0) * 0.5
        throttle.offer([tf("map", "odom"), tf("odom", "base_link", x=x)])
        out = throttle.poll(now)
        if out is not None:
            sent.append((now, out))
    snapshots = [(t, out) for t, out in sent if out.snapshot]
    deltas = [out for _, out in sent if not out.snapshot]
    # Deltas carry only what moved; map -> odom goes out in snapshots alone.
    assert deltas and all(names(out) == ["base_link"] for out in deltas)
    assert all(names(out) == ["odom", "base_link"] for _, out in snapshots)
    # While moving, one snapshot per period; after parking one more (the final position),
    # then nothing at all.
    times = [t for t, _ in snapshots]
    assert times[0] == 0.0
    assert all(b - a >= SNAPSHOT_PERIOD_S - 1e-9 for a, b in itertools.pairwise(times))
    assert times[-1] <= 5.0 + SNAPSHOT_PERIOD_S
    assert sent[-1][0] == times[-1]
    final = snapshots[-1][1].transforms[1]
    assert final.transform.translation.x == pytest.approx(2.5)
    assert throttle.stats.snapshots_out == len(snapshots)


def test_a_new_pair_makes_the_snapshot_stale() -> None:
    throttle = TfThrottle(TfSpec(max_rate_hz=10.0))
    throttle.offer([tf("map", "odom")])
    assert throttle.poll(0.0) is not None
    throttle.offer([tf("map", "odom"), tf("odom", "base_link")])
    assert names(throttle.poll(0.5)) == ["base_link"]  # at once, as a delta
    assert throttle.poll(1.0) is None
    # The relay's snapshot lacks base_link until the period allows a new one.
    later = throttle.poll(SNAPSHOT_PERIOD_S)
    assert later is not None and later.snapshot and names(later) == ["odom", "base_link"]


def test_a_forced_snapshot_goes_out_at_the_next_allowed_poll() -> None:
    throttle = TfThrottle(TfSpec(max_rate_hz=10.0))
    throttle.offer([tf("map", "odom")])
    throttle.poll(0.0)
    assert throttle.poll(30.0) is None  # parked: nothing, however long
    throttle.force_snapshot()  # a new connection
    out = throttle.poll(30.0)
    assert out is not None and out.snapshot and names(out) == ["odom"]
    assert throttle.poll(31.0) is None
    # The rate bound holds for snapshots too.
    throttle.force_snapshot()
    assert throttle.poll(30.05) is None
    assert throttle.poll(30.1) is not None


def test_nothing_is_forced_before_any_transform() -> None:
    throttle = TfThrottle(TfSpec())
    throttle.force_snapshot()
    assert throttle.poll(0.0) is None
