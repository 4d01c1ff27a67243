"""The fleet scenarios and the zenoh comparison, short, through the real router, server,
client and consumers.

``fleetctl build`` runs first (cached: a no-op when nothing changed), then one ``fleetctl e2e``
invocation runs every scenario with its baseline. The report must exist and every scenario
must have run. What is asserted here is what does not depend on how busy the machine is:
every no_drop message delivered in order, uplink bytes flat in the number of consumers,
recovery faster than the all-no_drop baseline. The absolute timing bars (recovery within
1 s, p99 latencies) are figures of a benchmark: the run reports them, exits non-zero when
one fails, and docs/e2e.md records them; they are never relaxed, only not turned into a
timed test.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import pytest

from fleetctl.cli.main import main

pytestmark = [
    pytest.mark.docker,
    # The module's one e2e run (build check, seven scenarios with their baselines) is
    # ~8-12 min on a 2-core host, over the suite's 600 s per test; a hang still ends.
    pytest.mark.timeout(1800),
    pytest.mark.skipif(shutil.which("docker") is None, reason="needs docker"),
]

SCENARIOS = ("dropout", "priority", "multi-consumer", "ramp", "peer", "peer-fanout",
             "replica-failure")


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, Path, dict[str, Any]]:
    assert main(["build"]) == 0
    out = tmp_path_factory.mktemp("e2e")
    argv = ["e2e", "--duration", "6", "--out", str(out)]
    for name in SCENARIOS:
        argv += ["--scenario", name]
    code = main(argv)
    doc = json.loads((out / "report.json").read_text())
    return code, out, {s["name"]: s for s in doc["scenarios"]}


def _criteria(result: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {c["name"]: c for c in result["criteria"]}


def test_every_scenario_ran_and_the_report_is_written(
        run: tuple[int, Path, dict[str, Any]]) -> None:
    code, out, results = run
    assert set(results) == set(SCENARIOS)
    for name, result in results.items():
        assert result["status"] in ("pass", "fail"), (name, result["notes"])
        assert result["criteria"], name
        assert (out / f"{name}-0.png").is_file()
    assert "| multi-consumer |" in (out / "report.md").read_text()
    all_pass = all(r["status"] == "pass" for r in results.values())
    assert (code == 0) == all_pass


def test_multi_consumer_uplink_is_flat_and_latency_holds(
        run: tuple[int, Path, dict[str, Any]]) -> None:
    result = run[2]["multi-consumer"]
    crits = _criteria(result)
    assert crits["uplink max/min over consumer counts"]["ok"], crits
    fleet = result["steps"]["fleetctl"]
    assert [s["consumers"] for s in fleet] == [1, 2, 4, 8, 16]
    # 5 Hz published. Every consumer count gets most of it; the exact rate is a figure of
    # the report (a CI run on a busy 2-core host once saw a step under 4 Hz).
    rates = [round(s["received_per_consumer_hz"], 2) for s in fleet]
    assert all(r > 2.5 for r in rates), rates


def test_dropout_no_drop_events_arrive_whole_and_in_order(
        run: tuple[int, Path, dict[str, Any]]) -> None:
    crits = _criteria(run[2]["dropout"])
    assert crits["no_drop events missing"]["ok"], crits
    assert crits["no_drop events out of order or duplicated"]["ok"], crits


def test_dropout_recovers_faster_than_the_all_no_drop_baseline(
        run: tuple[int, Path, dict[str, Any]]) -> None:
    crits = _criteria(run[2]["dropout"])
    recovery = crits["recovery_s (worst droppable topic)"]["value"]
    assert 0 < recovery < 10, crits  # measured: the link came back within the run
    assert crits["baseline_recovery_s / recovery_s"]["ok"], crits


def test_ramp_and_priority_measure_the_high_priority_topic(
        run: tuple[int, Path, dict[str, Any]]) -> None:
    # Their bars (p99 < 100 ms during the ramp, < 15 ms on 6 Mbit/s) are not met yet on this
    # machine (docs/e2e.md has the figures): the run reports them as failures and exits 1;
    # here we check that they were measured on enough messages.
    for name in ("ramp", "priority"):
        crit = run[2][name]["criteria"][0]
        assert crit["name"].startswith("high-priority p99_ms"), crit
        assert crit["value"] == crit["value"], name  # not NaN: the topic was received
        stats = run[2][name]["stats"]["fleetctl"]
        assert min(st["count"] for st in stats.values()) > 5, (name, stats)


def test_video_is_decoded_never_from_a_broken_reference_and_follows_the_link(
        run: tuple[int, Path, dict[str, Any]]) -> None:
    camera = "/robot1/camera/image_raw"
    crits = _criteria(run[2]["dropout"])
    # Correctness, not timing: every frame the consumer's decoder showed had its whole
    # reference chain (and at least one frame was shown).
    assert crits[f"video {camera}: frames shown from a broken reference"]["ok"], crits
    back = crits[f"video {camera}: first live frame shown after the restore (s)"]["value"]
    assert 0 <= back < 10, crits  # measured: frames were shown again after the cut
    ramp = _criteria(run[2]["ramp"])
    slow = ramp["video Mbit/s at 4 Mbit/s (last 2 s)"]["value"]
    assert slow > 0, ramp  # frames arrived at the end of the ramp: measured


def test_peer_measures_every_variant_after_every_cut(
        run: tuple[int, Path, dict[str, Any]]) -> None:
    result = run[2]["peer"]
    assert set(result["trials"]) == {"fleetctl", "zenoh-default", "zenoh-best"}, result["notes"]
    for variant, trials in result["trials"].items():
        assert len(trials) == 2, variant  # cuts of 5 and 0.5 s at this duration
        # Messages flowed again after every restore, through fleetctl and through zenoh.
        assert all(t["first_s"] < 10 for t in trials), (variant, trials)
    assert all(0 < b < 4e6 for b in result["uplink_bit_s"].values()), result["uplink_bit_s"]
    # The robot's log of this scenario is kept apart from the fan-out's robot (same load,
    # run after it): its first connection and the new one after the 5 s cut are there.
    logs = run[1] / "raw" / "logs"
    robot_log = (logs / "peer-fleetctl-robot.log").read_text()
    assert robot_log.count("connected to ") >= 2, robot_log[-2000:]
    assert (logs / "fanout-fleetctl-robot.log").is_file()
    # The robot's own view, read from its stats during the first cut and after the last
    # trial (whether its slow-link rule switched on a reconnect): pose and scan sent.
    views = [n for n in result["notes"] if n.startswith("fleetctl robot from its connect")]
    assert [v.split(":", 1)[0] for v in views] == [
        "fleetctl robot from its connect to the first cut",
        "fleetctl robot from its connect to the end of the trials"], views
    for view in views:
        assert "link rate " in view and "/robot1/scan " in view and "/robot1/pose " in view, view
    # The floor in two rounds at this duration (three at full length), each variant with a
    # new robot in the second: every round gave a p50, and the criterion is the medians'.
    (floors,) = [n for n in result["notes"] if n.startswith("latency floor p50 by round")]
    for variant in ("fleetctl", "zenoh-default", "zenoh-best"):
        rounds = floors.split(f"{variant} ", 1)[1].split(" (median", 1)[0].split(" / ")
        assert len(rounds) == 2 and all(0 < float(x) < 1000 for x in rounds), floors
    assert (logs / "peer-floor2-fleetctl-robot.log").is_file()


def test_peer_fanout_reaches_every_consumer(run: tuple[int, Path, dict[str, Any]]) -> None:
    rounds = run[2]["peer-fanout"]["rounds"]
    assert set(rounds) == {"fleetctl", "zenoh-default", "zenoh-best"}
    for variant, sweeps in rounds.items():
        assert len(sweeps) == 2, variant  # two rounds below 30 s, the variants rotated
        for counts in sweeps:
            assert [s["consumers"] for s in counts] == [1, 4, 16], variant
            # 30 msg/s published (scan 10 Hz + pose 20 Hz) and the link has room for all.
            assert all(s["received_per_consumer_hz"] > 25 for s in counts), (variant, counts)
    names = [c["name"] for c in run[2]["peer-fanout"]["criteria"]]
    assert all(n.endswith(", medians of the rounds") for n in names), names
    views = [n for n in run[2]["peer-fanout"]["notes"] if n.startswith("fleetctl robot at ")]
    assert [v.split(":", 1)[0] for v in views] == [
        f"fleetctl robot at {n} consumer(s)" for n in (1, 4, 16)], views
    assert all("link rate " in v and "/robot1/scan " in v for v in views), views
    rounds_seen = [n.split(":", 1)[0] for n in run[2]["peer-fanout"]["notes"]
                   if n.startswith("fleetctl robot in round ")]
    assert rounds_seen == ["fleetctl robot in round 2, from its connect"]


def test_replica_failure_moves_the_robot_to_b_with_every_event(
        run: tuple[int, Path, dict[str, Any]]) -> None:
    """What does not depend on the host's speed: the viewer on B stayed connected, the
    events arrived whole, in order, once, and both the failover and the NATS node's loss
    were overcome (their times are figures of the report, with their bars)."""
    result = run[2]["replica-failure"]
    crits = _criteria(result)
    assert crits["viewer on B disconnected"]["ok"], crits
    assert crits["no_drop events missing"]["ok"], crits
    assert crits["no_drop events out of order or duplicated"]["ok"], crits
    assert math.isfinite(result["failover_s"]) and math.isfinite(result["nats_resume_s"])
    # The session's viewer on A resumed its session on B with every event it missed.
    assert crits["session resumed on B: no_drop events missing"]["ok"], crits
    assert crits["session resumed on B: events out of order or duplicated"]["ok"], crits
