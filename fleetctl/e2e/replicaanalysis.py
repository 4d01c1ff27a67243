"""The ``replica-failure`` result (issue 15), from the samples of the viewer on replica B.

Pure: samples and the run's marks in, criteria, notes and plots out
(:mod:`fleetctl.e2e.replicascenario` runs it).

Definitions (docs/e2e.md repeats them):

- **failover_s**: from relay A's kill to the first pose *published after the kill* that the
  viewer on B received: the robot is relaying through B again.
- **nats_resume_s**: the same from the kill of relay A's NATS node: frames cross from A
  to B through NATS again.
- **latency ratio**: the pose's p99 over the whole run (both kills included) over its p99
  in the quiet phase before them. The pose is what a viewer watches (latest-only); the
  no_drop events are judged by their own criteria, since a resend after a failover delays
  them by design.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from fleetctl.e2e.analysis import crit, expected_no_drop, latency_line, stats_dict, status_of
from fleetctl.e2e.metrics import LatencyStats, by_topic, check_order
from fleetctl.e2e.samples import Sample

FAILOVER_BOUND_S = 1.0
LATENCY_RATIO_BOUND = 2.0
# A NATS node dies: its replica notices (a closed socket at once, a silent host after the
# pings: natsfanout.PING_INTERVAL_S) and reconnects to another listed node.
NATS_RESUME_BOUND_S = 5.0


def first_after(samples: Sequence[Sample], mark_ns: int) -> float:
    """Seconds from *mark_ns* to the receipt of the first sample published after it
    (``inf``: none arrived)."""
    recv = [s.recv_time_ns for s in samples if s.publish_time_ns >= mark_ns]
    return (min(recv) - mark_ns) / 1e9 if recv else math.inf


def replica_failure(samples: Sequence[Sample], pose: str, events: str,
                    published_events: Mapping[str, int], marks: Mapping[str, int],
                    viewer_stayed: bool, resumed: Sequence[Sample] = ()) -> dict[str, Any]:
    """The result of one run.

    Args:
        samples: The viewer on B's samples (no_drop duplicates already dropped, as an
            application receiving through ``RobotLink`` would).
        pose: The latest-only topic the latency is judged on.
        events: The no_drop topic that must arrive whole, in order, once.
        published_events: What the load publisher published on *events*
            (``first_seq``, ``last_seq``).
        marks: ``t0``, ``nats_kill``, ``relay_kill``, ``end`` (ns since the epoch).
        viewer_stayed: The viewer on B's connection never closed.
        resumed: The samples of the session's viewer that started on A and resumed its
            session on B after A's kill (duplicates dropped likewise); its events must
            arrive whole, in order, once.
    """
    topics = by_topic(samples)
    poses = topics.get(pose, [])
    quiet = [s for s in poses if s.recv_time_ns < marks["nats_kill"]]
    run = [s for s in poses if s.recv_time_ns <= marks["end"]]
    quiet_p99 = LatencyStats.of(quiet).p99_ms
    run_p99 = LatencyStats.of(run).p99_ms
    ratio = run_p99 / quiet_p99 if quiet_p99 > 0 else math.inf
    failover = first_after(poses, marks["relay_kill"])
    nats_resume = first_after([s for s in poses if s.publish_time_ns < marks["relay_kill"]],
                              marks["nats_kill"])
    got = topics.get(events, [])
    order = check_order(got, expected_no_drop(got, published_events))
    session_got = [s for s in resumed if s.topic == events]
    session = check_order(session_got, expected_no_drop(session_got, published_events))
    criteria = [
        crit("robot relaying through B after relay A's kill (s)", failover,
             FAILOVER_BOUND_S, failover <= FAILOVER_BOUND_S),
        crit("viewer on B disconnected", 0.0 if viewer_stayed else 1.0, 0, viewer_stayed),
        crit("pose p99 over the run / quiet p99", ratio, LATENCY_RATIO_BOUND,
             ratio < LATENCY_RATIO_BOUND),
        crit("no_drop events missing", order.missing, 0, order.missing == 0),
        crit("no_drop events out of order or duplicated",
             order.out_of_order + order.duplicates, 0,
             order.out_of_order == 0 and order.duplicates == 0),
        crit("frames cross replicas again after a NATS node's kill (s)", nats_resume,
             NATS_RESUME_BOUND_S, nats_resume <= NATS_RESUME_BOUND_S),
        crit("session resumed on B: no_drop events missing", session.missing, 0,
             session.missing == 0 and session.received > 0),
        crit("session resumed on B: events out of order or duplicated",
             session.out_of_order + session.duplicates, 0,
             session.out_of_order == 0 and session.duplicates == 0),
    ]
    t0 = marks["t0"]
    notes = [
        f"pose at the viewer on B: quiet p99 {quiet_p99:.1f} ms (n={len(quiet)}), whole run "
        f"p99 {run_p99:.1f} ms (n={len(run)})",
        f"relay A killed at {(marks['relay_kill'] - t0) / 1e9:.1f} s: first pose through B "
        f"{failover:.3f} s later; its NATS node killed at "
        f"{(marks['nats_kill'] - t0) / 1e9:.1f} s: frames crossed again {nats_resume:.3f} s "
        "later",
        f"no_drop events: received {order.received}, missing {order.missing}, out of order "
        f"{order.out_of_order}, duplicates {order.duplicates}",
        f"session's viewer (A, then B after A's kill): events received {session.received}, "
        f"missing {session.missing}, out of order {session.out_of_order}, duplicates "
        f"{session.duplicates}",
    ]
    spans = [[(marks["nats_kill"] - t0) / 1e9, (marks["nats_kill"] - t0) / 1e9 + 0.05,
              "NATS node killed"],
             [(marks["relay_kill"] - t0) / 1e9, (marks["relay_kill"] - t0) / 1e9 + 0.05,
              "relay A killed"]]
    plots = [{"title": "replica-failure: latency at the viewer on B", "xlabel":
              "publish time (s)", "ylabel": "latency (ms)", "logy": True, "marker": ".",
              "style": "", "spans": spans,
              "lines": {t: latency_line(ss, t0) for t, ss in topics.items()}}]
    return {"name": "replica-failure", "status": status_of(criteria), "criteria": criteria,
            "notes": notes, "plots": plots,
            "stats": {t: stats_dict(ss) for t, ss in topics.items()},
            "failover_s": failover, "nats_resume_s": nats_resume}
