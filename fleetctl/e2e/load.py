"""The e2e load publisher: a real rclpy node publishing a scenario's topics.

Runs inside the robot container next to ``fleetctl client`` (or alone, for the native DDS
baseline)::

    python -m fleetctl.e2e.load --profile dropout --out /e2e/out/published.json

Each topic is published by its own ROS timer at the profile's rate (by one clock at fixed
phases when the profile spreads them, :func:`phase_schedule`); every message carries
its publish time and per-topic sequence number (:mod:`fleetctl.e2e.payloads`), stamped just
before serialization. Messages are serialized with rosbags and published as CDR bytes, so
large arrays are never converted element by element. On SIGTERM/SIGINT it stops and writes
``{remote_topic: {"first_seq", "last_seq", "count"}}`` to ``--out``: what consumers must
have received for no_drop topics.

This module and :mod:`.ddssub` use rclpy (only in the client image, where it exists) through
:mod:`fleetctl.client.ros`, imported inside functions; nothing else in :mod:`fleetctl.e2e`
does.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fleetctl.e2e import payloads
from fleetctl.e2e.profiles import Profile, TopicLoad, profile
from fleetctl.errors import FleetError


class _Counts:
    """Published sequence numbers per wire topic."""

    def __init__(self) -> None:
        self.by_topic: dict[str, dict[str, int]] = {}

    def add(self, topic: str, seq: int) -> None:
        entry = self.by_topic.setdefault(topic, {"first_seq": seq, "last_seq": seq, "count": 0})
        entry["last_seq"] = seq
        entry["count"] += 1


def phase_schedule(p: Profile) -> tuple[float, list[tuple[int, int]]] | None:
    """One clock for every topic of a profile that spreads its phases, else None.

    Returns the clock's period and, per topic, ``(every, at)``: the topic publishes on the
    clock's ticks ``k`` with ``k % every == at``. The clock's period is the shortest period
    over the number of topics, and topic *i* takes slot *i*: the peer load's scan at 0 and
    its pose at 25 ms, every message 25 ms from the other topic's. One timer, not a timer
    per topic started later: a timer's phase is set where it is created, and a one-shot
    that creates it fires as late as the executor's first spin (6 ms off in a trial).

    Raises:
        FleetError: a topic's period is not a whole number of the clock's.
    """
    if not p.spread_phases or not p.topics:
        return None
    base = min(1.0 / t.rate_hz for t in p.topics) / len(p.topics)
    slots = []
    for i, t in enumerate(p.topics):
        every = round(1.0 / t.rate_hz / base)
        if abs(every * base - 1.0 / t.rate_hz) > 1e-9:  # base <= every period: every >= 1
            raise FleetError(f"profile {p.name}: {t.topic} at {t.rate_hz:g} Hz is not a "
                             f"whole number of {base * 1e3:g} ms periods")
        slots.append((every, i))
    return base, slots


def _publisher(node: Any, load: TopicLoad, ts: Any, counts: _Counts) -> Callable[[], None]:
    """A publisher of *load* on *node*; returns its tick (build, stamp, publish one)."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    from fleetctl.client.ros.msgtypes import message_class

    # Reliable with room for a burst: the subscriber (client or DDS consumer) decides how
    # much it keeps; the publisher must not be the one dropping.
    qos = QoSProfile(  # type: ignore[no-untyped-call]  # rclpy ships no type hints
        history=HistoryPolicy.KEEP_LAST, depth=100 if load.no_drop else 5,
        reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(message_class(load.type), load.topic, qos)
    seq = 0

    def tick() -> None:
        nonlocal seq
        seq += 1
        msg = payloads.build(ts, load.type, load.size_bytes, seq, time.time_ns())
        pub.publish(bytes(ts.serialize_cdr(msg, load.type)))
        counts.add(load.remote_topic, seq)

    return tick


def _start_timers(node: Any, p: Profile, ticks: list[Callable[[], None]]) -> None:
    schedule = phase_schedule(p)
    if schedule is None:  # a timer per topic, at whatever phase its creation gives it
        for load, tick in zip(p.topics, ticks, strict=True):
            node.create_timer(1.0 / load.rate_hz, tick)
        return
    base, slots = schedule
    k = 0

    def clock() -> None:
        # rcl skips the ticks of a late executor; the topics stay on one grid either way.
        nonlocal k
        for tick, (every, at) in zip(ticks, slots, strict=True):
            if k % every == at:
                tick()
        k += 1

    node.create_timer(base, clock)


def run(p: Profile, out: Path | None) -> dict[str, dict[str, int]]:
    """Publish *p*'s topics until SIGTERM/SIGINT; returns (and writes) what was published."""
    from fleetctl.client.ros.spin import spin_until_signal
    from fleetctl.wire.registry import TypeRegistry

    ts = TypeRegistry.default().typestore
    counts = _Counts()

    def setup(node: Any) -> None:
        _start_timers(node, p, [_publisher(node, load, ts, counts) for load in p.topics])
        print(f"e2e load: publishing {[t.topic for t in p.topics]}", flush=True)

    spin_until_signal(f"e2e_load_{p.name.replace('-', '_')}", setup)
    if out is not None:
        out.write_text(json.dumps(counts.by_topic))
    return counts.by_topic


def main(argv: list[str] | None = None) -> int:
    """Command line entry point (``python -m fleetctl.e2e.load``)."""
    parser = argparse.ArgumentParser(prog="python -m fleetctl.e2e.load")
    parser.add_argument("--profile", required=True)
    parser.add_argument("--out", type=Path, default=None, help="published.json to write")
    args = parser.parse_args(argv)
    try:
        run(profile(args.profile), args.out)
    except FleetError as exc:
        print(f"e2e load: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
