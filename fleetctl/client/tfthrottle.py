"""TF republishing with tf2_web_republisher's semantics (pure: no rclpy, no I/O).

A robot's ``/tf`` carries tens of frames at 50-100 Hz, most of which barely move between
messages. :class:`TfThrottle` keeps, per (parent, child) pair, the latest transform and
the one last sent, and at most ``max_rate_hz`` times per second emits one message holding
every pair that moved more than ``translation_delta_m`` or turned more than
``rotation_delta_rad`` since its last sent value (a pair seen for the first time always
moves). What a receiver holds is therefore, right after each emission, within the deltas
of the newest transform the robot had; between emissions a change waits at most one
period (1 / ``max_rate_hz``).

Late receivers. tf2_web_republisher throttles per client, so each new client gets every
transform once; here the robot throttles once for all receivers, so a pair that stopped
moving (a localizer's constant ``map -> odom``, a parked robot's ``odom -> base_link``)
would never reach a viewer who subscribes after it was last sent. So some emissions are
*snapshots*: every known pair's newest transform, sent latched. The relay keeps the
newest latched message of the topic (docs/server.md) and gives it to every later
subscriber first, then the deltas follow. A snapshot goes out in place of a delta when
the last one is out of date (a pair was sent since, or a new pair appeared), at most
every :data:`SNAPSHOT_PERIOD_S`, and at once after :meth:`TfThrottle.force_snapshot` (a
new connection: a restarted server holds nothing). A parked robot sends nothing after
its snapshot; a moving one pays one message of every pair per period.

tf2_web_republisher (RobotWebTools) looks transforms up per requested (target, source)
pair on a timer and compares with bullet's ``Quaternion::angle``, which is *half* the
rotation angle; here the raw edges are compared and the rotation delta is the full angle
between the two orientations, ``2 acos |q1 . q2|``, so a ``rotation_delta_rad`` of 0.01 is
what it says.

:class:`StaticTf` accumulates ``/tf_static``: every static broadcaster publishes its own
(latched) message, and a receiver needs all of them, so the robot sends one message with
every static pair, again whole (and latched) whenever a pair appears or changes.

Transforms are duck-typed ``geometry_msgs/msg/TransformStamped`` objects (rosbags
messages or anything with ``header.frame_id``, ``child_frame_id`` and
``transform.translation.{x,y,z}`` / ``transform.rotation.{x,y,z,w}``): they are sent on
unchanged, never rebuilt.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from fleetctl.client.config import TfSpec

# A robot has tens to a few hundred frames; a publisher inventing frame names (a bug, or a
# per-object tracker) must not grow the table without bound. Excess pairs are counted.
MAX_PAIRS = 4096

# How stale the relay's copy of the TF tree may get while pairs move: a viewer subscribing
# now may see a pair that stopped moving within this long at an older value until the next
# snapshot. Moving pairs are corrected by the next delta (one period).
SNAPSHOT_PERIOD_S = 2.0

Pair = tuple[str, str]  # (parent, child), without tf2's optional leading '/'
Pose = tuple[float, float, float, float, float, float, float]  # x y z qx qy qz qw


def pair_of(transform: Any) -> Pair:
    """The (parent, child) frame ids of a TransformStamped (tf2 strips a leading '/')."""
    return (str(transform.header.frame_id).lstrip("/"), str(transform.child_frame_id).lstrip("/"))


def pose_of(transform: Any) -> Pose:
    """The translation (m) and unit quaternion of a TransformStamped.

    Raises:
        ValueError: a component is not finite, or the quaternion has zero length.
    """
    t, q = transform.transform.translation, transform.transform.rotation
    values = (float(t.x), float(t.y), float(t.z), float(q.x), float(q.y), float(q.z),
              float(q.w))
    if not all(math.isfinite(v) for v in values):
        raise ValueError("a component is not finite")
    norm = math.sqrt(sum(v * v for v in values[3:]))
    if norm == 0.0:
        raise ValueError("zero quaternion")
    x, y, z, qx, qy, qz, qw = values
    return (x, y, z, qx / norm, qy / norm, qz / norm, qw / norm)


def translation_m(a: Pose, b: Pose) -> float:
    """Distance between two poses' origins (m)."""
    return math.sqrt((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2)


def rotation_rad(a: Pose, b: Pose) -> float:
    """Angle of the rotation taking one orientation to the other (rad, 0..pi).

    q and -q are the same orientation, hence the absolute value of the dot product.
    """
    dot = abs(a[3] * b[3] + a[4] * b[4] + a[5] * b[5] + a[6] * b[6])
    return 2.0 * math.acos(min(1.0, dot))


@dataclass
class TfStats:
    """Counters of the republisher.

    Attributes:
        transforms_in: transforms received on ``/tf``.
        messages_out: messages emitted (one per tick with a change).
        transforms_out: transforms in those messages.
        invalid: transforms dropped for a non-finite value or a zero quaternion.
        pairs_over_limit: transforms dropped because :data:`MAX_PAIRS` pairs are known.
        static_in: transforms received on ``/tf_static``.
        static_out: whole ``tf_static`` messages emitted.
        snapshots_out: of ``messages_out``, latched snapshots of every pair.
    """

    transforms_in: int = 0
    messages_out: int = 0
    transforms_out: int = 0
    invalid: int = 0
    pairs_over_limit: int = 0
    static_in: int = 0
    static_out: int = 0
    snapshots_out: int = 0


@dataclass(frozen=True)
class TfEmission:
    """One ``/tf`` message to send: its transforms, and whether it is a latched snapshot of
    every pair (see the module docstring) or the pairs that moved."""

    transforms: list[Any]
    snapshot: bool


class TfThrottle:
    """Per-pair delta filter plus an overall rate bound for ``/tf``.

    Args:
        spec: The deltas and the rate bound.
        stats: Counters to update (shared with :class:`StaticTf`); None: its own.
        snapshot_period_s: Least time between two snapshots while pairs move.
    """

    def __init__(self, spec: TfSpec, stats: TfStats | None = None,
                 snapshot_period_s: float = SNAPSHOT_PERIOD_S) -> None:
        self.spec = spec
        self.stats = stats or TfStats()
        self.period_s = 1.0 / spec.max_rate_hz
        self.snapshot_period_s = snapshot_period_s
        self._latest: dict[Pair, tuple[Any, Pose]] = {}
        self._sent: dict[Pair, Pose] = {}
        self._changed: set[Pair] = set()
        self._next_s = -math.inf
        self._snapshot_s = -math.inf
        # The relay's latched copy misses something: a pair sent since, or a new pair.
        self._snapshot_stale = False
        self._snapshot_forced = False

    def offer(self, transforms: Iterable[Any]) -> None:
        """Take the transforms of one ``/tf`` message (newer replace older per pair)."""
        for transform in transforms:
            self.stats.transforms_in += 1
            try:
                pair, pose = pair_of(transform), pose_of(transform)
            except (ValueError, TypeError, AttributeError):
                self.stats.invalid += 1
                continue
            if pair not in self._latest:
                if len(self._latest) >= MAX_PAIRS:
                    self.stats.pairs_over_limit += 1
                    continue
                self._snapshot_stale = True  # the relay's snapshot lacks it
            self._latest[pair] = (transform, pose)
            if self._moved(pair, pose):
                self._changed.add(pair)

    def _moved(self, pair: Pair, pose: Pose) -> bool:
        sent = self._sent.get(pair)
        if sent is None:
            return True
        return (translation_m(sent, pose) > self.spec.translation_delta_m
                or rotation_rad(sent, pose) > self.spec.rotation_delta_rad)

    def force_snapshot(self) -> None:
        """Send a snapshot at the next :meth:`poll` the rate allows (a new connection)."""
        self._snapshot_forced = True

    def _snapshot_due(self, now_s: float) -> bool:
        if not self._latest:
            return False
        return self._snapshot_forced or (
            self._snapshot_stale and now_s - self._snapshot_s >= self.snapshot_period_s)

    def poll(self, now_s: float) -> TfEmission | None:
        """The message to send now, or None (nothing moved, or too soon).

        Call after :meth:`offer` (low latency when the rate allows) and on a timer at
        ``max_rate_hz`` (so a pending change never waits longer than one period).

        Args:
            now_s: Monotonic clock in seconds.
        """
        if now_s < self._next_s:
            return None
        snapshot = self._snapshot_due(now_s)
        if not snapshot and not self._changed:
            return None
        out = []
        # Sorted: the same input gives the same bytes.
        for pair in sorted(self._latest) if snapshot else sorted(self._changed):
            transform, pose = self._latest[pair]
            # Checked again: a pair that moved and came back within the period stays.
            if snapshot or self._moved(pair, pose):
                self._sent[pair] = pose
                out.append(transform)
        self._changed.clear()
        if not out:
            return None
        if snapshot:
            self._snapshot_s = now_s
            self._snapshot_stale = self._snapshot_forced = False
            self.stats.snapshots_out += 1
        else:
            self._snapshot_stale = True
        # From now, not from the due time: two messages are never closer than one period,
        # so the bound holds however the caller's timer and /tf callbacks interleave.
        self._next_s = now_s + self.period_s
        self.stats.messages_out += 1
        self.stats.transforms_out += len(out)
        return TfEmission(out, snapshot)

    def sent_pose(self, pair: Pair) -> Pose | None:
        """The pose last emitted for *pair* (what a receiver holds), or None."""
        return self._sent.get(pair)

    def latest_pose(self, pair: Pair) -> Pose | None:
        """The newest pose received for *pair*, or None."""
        entry = self._latest.get(pair)
        return None if entry is None else entry[1]

    def __len__(self) -> int:
        return len(self._latest)


class StaticTf:
    """All static transforms, re-sent whole when one appears or changes.

    Args:
        stats: Counters to update (shared with :class:`TfThrottle`); None: its own.
    """

    def __init__(self, stats: TfStats | None = None) -> None:
        self.stats = stats or TfStats()
        self._pairs: dict[Pair, tuple[Any, Pose]] = {}

    def offer(self, transforms: Iterable[Any]) -> list[Any] | None:
        """Take one ``/tf_static`` message; return every static transform if something is
        new or different (a broadcaster re-publishing the same set returns None)."""
        changed = False
        for transform in transforms:
            self.stats.static_in += 1
            try:
                pair, pose = pair_of(transform), pose_of(transform)
            except (ValueError, TypeError, AttributeError):
                self.stats.invalid += 1
                continue
            old = self._pairs.get(pair)
            if old is not None and old[1] == pose:
                continue
            if old is None and len(self._pairs) >= MAX_PAIRS:
                self.stats.pairs_over_limit += 1
                continue
            self._pairs[pair] = (transform, pose)
            changed = True
        if not changed:
            return None
        self.stats.static_out += 1
        return [self._pairs[pair][0] for pair in sorted(self._pairs)]

    def __len__(self) -> int:
        return len(self._pairs)
