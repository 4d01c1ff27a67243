"""The peer scenario's analysis on hand-made samples."""

from __future__ import annotations

import math

import pytest

from fleetctl.e2e import peeranalysis
from fleetctl.e2e.samples import Sample

S = 1_000_000_000
MS = 1_000_000


def _stream(topic: str, start_s: float, end_s: float, period_s: float, latency_ms: float,
            gaps: list[tuple[float, float]], stale_at: list[float] = ()) -> list[Sample]:
    out, t, seq = [], start_s, 0
    while t < end_s:
        seq += 1
        if not any(a <= t < b for a, b in gaps):
            pub = int(t * S)
            out.append(Sample(topic, seq, pub, pub + int(latency_ms * MS), 100))
        t += period_s
    for r in stale_at:  # published before the restore at r, received just after it
        out.append(Sample(topic, 0, int((r - 0.5) * S), int((r + 0.01) * S), 100))
    return out


def _run(recover_after_s: float, stale: bool = False) -> peeranalysis.VariantRun:
    trials = [(10 * S, 15 * S, 21 * S), (21 * S, 26 * S, 32 * S)]
    gaps = [(10.0, 15.0 + recover_after_s), (21.0, 26.0 + recover_after_s)]
    samples = _stream("/r/pose", 0.0, 32.0, 0.05, 2.0, gaps, [15.0] if stale else [])
    return peeranalysis.VariantRun(samples, 0, trials, 0.45e6, {})


def test_every_trial_is_measured_against_the_steady_phase() -> None:
    (t1, t2) = peeranalysis.trials_of(_run(0.08), ["/r/pose"])
    assert 0.08 <= t1.recovery_s["/r/pose"] < 0.14
    assert 0.08 <= t2.recovery_s["/r/pose"] < 0.14  # no steady phase before the second cut
    assert t1.stale == 0 and t1.first_s == t1.recovery_s["/r/pose"]


def test_stale_messages_and_the_criteria() -> None:
    runs = {"fleetctl": _run(0.05, stale=True), "zenoh-best": _run(0.4)}
    result = peeranalysis.peer(runs, ["/r/pose"])
    crits = {c["name"]: c for c in result["criteria"]}
    assert crits["fleetctl stale messages after the restores"]["value"] == 1
    # How old it was at the restore is said, trial by trial (published 0.5 s before it).
    (t1, t2) = result["trials"]["fleetctl"]
    assert t1["stale"] == 1 and t1["stale_before_s"] == pytest.approx(0.5)
    assert t2["stale"] == 0 and t2["stale_before_s"] == 0
    assert "stale 1 (published up to 500.0 ms before the restore)" in result["notes"][0]
    assert crits["fleetctl recovery, worst topic of the worst trial (s)"]["ok"]
    factor = crits["zenoh-best / fleetctl recovery, worst trial"]["value"]
    assert 4 <= factor < 10
    assert crits["fleetctl steady uplink (Mbit/s)"]["ok"]
    assert result["status"] == "fail"  # the stale message
    assert math.isclose(result["floor_p50_ms"]["fleetctl"], 2.0, abs_tol=0.01)


def test_bytes_per_message_against_the_cdr() -> None:
    fleet = [Sample("/r/scan", 1, 0, 1, 5984)]
    zen = [Sample("/r/scan", 1, 0, 1, 5816)]
    runs = {"fleetctl": peeranalysis.VariantRun(fleet, 0, [], 0.36e6, {}, messages_per_s=30),
            "zenoh-best": peeranalysis.VariantRun(zen, 0, [], 0.54e6, {}, messages_per_s=30)}
    assert peeranalysis.bytes_note(runs) == (
        "bytes per message (frame as relayed): /r/scan fleetctl 5984 (CDR 5816, +168); "
        "on the uplink, all overheads included: fleetctl 1500, zenoh-best 2250")
    runs["fleetctl"] = peeranalysis.VariantRun(fleet, 0, [], 0.36e6, {})  # rate unknown
    assert "fleetctl 1500" not in peeranalysis.bytes_note(runs)


def test_trial_cuts_and_rounds_short_and_full_length() -> None:
    from fleetctl.e2e.peerscenario import fanout_rounds, floor_rounds, trial_cuts

    assert trial_cuts(6) == (5.0, 0.5)
    full = trial_cuts(30)
    assert full.count(5.0) >= 10 and 0.5 in full and 30.0 in full
    # CI's short run still takes every path: a rotated floor round and a second sweep.
    assert (floor_rounds(6), fanout_rounds(6)) == (2, 2)
    assert (floor_rounds(30), fanout_rounds(30)) == (3, 3)


def test_each_trial_knows_its_limit_and_the_stack_s_share_past_it() -> None:
    # 20 Hz from t=0: the next publish after each restore (15 s, 26 s) is at once; the
    # stream is back 0.08 s after it with 2 ms latency.
    t1 = peeranalysis.trials_of(_run(0.08), ["/r/pose"])[0]
    assert t1.limit_s["/r/pose"] == pytest.approx(0.002, abs=1e-6)
    assert 0.078 <= t1.past_limit_s <= 0.14
    runs = {"fleetctl": _run(0.02), "zenoh-best": _run(0.4)}  # back at 15.05 and 15.4 s
    result = peeranalysis.peer(runs, ["/r/pose"])
    note = next(n for n in result["notes"] if n.startswith("recovery past the physical limit"))
    assert "fleetctl 0.050-0.050 s" in note and "zenoh-best 0.400-0.400 s" in note
    assert result["trials"]["fleetctl"][0]["limit_s"] == {"/r/pose": t1.limit_s["/r/pose"]}
    no_limit = peeranalysis.Trial({"/r/pose": 0.1}, 0.1, 0)
    assert math.isnan(no_limit.past_limit_s)


def test_the_floor_is_the_median_of_the_rounds() -> None:
    """A slow minute in one round (fleetctl's own run at 4 ms) does not decide the floor:
    the median of the rounds does, and the note gives every round and its ratio."""
    import dataclasses

    fleet = dataclasses.replace(_run(0.05), floor_rounds_ms=(1.5, 1.6))
    fleet = dataclasses.replace(fleet, samples=[
        dataclasses.replace(s, recv_time_ns=s.publish_time_ns + 4 * MS) for s in fleet.samples])
    zenoh = dataclasses.replace(_run(0.4), floor_rounds_ms=(1.8, 1.7))
    result = peeranalysis.peer({"fleetctl": fleet, "zenoh-best": zenoh}, ["/r/pose"])
    assert result["floor_p50_ms"] == {"fleetctl": 1.6, "zenoh-best": 1.8}
    crits = {c["name"]: c for c in result["criteria"]}
    floor = crits["fleetctl latency floor p50 / zenoh's best p50 (medians of the rounds)"]
    assert floor["ok"] and floor["value"] == pytest.approx(1.6 / 1.8)
    (note,) = [n for n in result["notes"] if n.startswith("latency floor p50 by round")]
    assert "fleetctl 4.00 / 1.50 / 1.60 (median 1.60)" in note
    assert "zenoh-best 2.00 / 1.80 / 1.70 (median 1.80)" in note
    assert note.endswith("fleetctl / lowest zenoh by round: 2.00x, 0.83x, 0.94x")
    # Without further rounds the floor is the run's own, as before.
    alone = peeranalysis.peer({"fleetctl": _run(0.05), "zenoh-best": _run(0.4)}, ["/r/pose"])
    assert alone["floor_p50_ms"]["fleetctl"] == pytest.approx(2.0, abs=0.01)


def _sweep(p50s_ms: tuple[float, float]) -> list[dict[str, object]]:
    """One fan-out round: 1 and 16 consumers, the pose faster than the scan."""
    return [{"consumers": n, "received_per_consumer_hz": 30.0,
             "topics": {"/r/pose": {"p50_ms": x - 0.2, "p99_ms": x + 1},
                        "/r/scan": {"p50_ms": x, "p99_ms": x + 2}}}
            for n, x in zip((1, 16), p50s_ms, strict=True)]


def test_the_fan_out_is_the_median_of_the_rounds() -> None:
    """As the floor: one slow round (fleetctl's first, at one consumer) does not decide;
    each variant's median over the rounds does, per consumer count, on the slower topic."""
    rounds = {"fleetctl": [_sweep((2.5, 2.2)), _sweep((1.5, 2.4)), _sweep((1.6, 2.3))],
              "zenoh-default": [_sweep((1.9, 2.9)), _sweep((1.7, 2.8)), _sweep((1.8, 2.7))],
              "zenoh-best": [_sweep((1.4, 2.5)), _sweep((1.7, 2.2)), _sweep((1.9, 2.0))]}
    result = peeranalysis.fanout(rounds)
    crits = {c["name"]: c for c in result["criteria"]}
    one = crits["fleetctl / zenoh's best p50 at 1 consumer(s) (fewest), medians of the rounds"]
    assert one["ok"] and one["value"] == pytest.approx(1.6 / 1.7)  # zenoh-best's median
    most = crits["fleetctl / zenoh's best p50 at 16 consumer(s) (most), medians of the rounds"]
    assert not most["ok"] and most["value"] == pytest.approx(2.3 / 2.2)
    assert result["status"] == "fail"
    (note,) = [n for n in result["notes"] if n.startswith("fan-out p50 at 1 consumer(s)")]
    assert "fleetctl 2.50 / 1.50 / 1.60 (median 1.60)" in note
    assert note.endswith("fleetctl / lowest zenoh by round: 1.79x, 0.88x, 0.89x")
    assert result["steps"]["fleetctl"] == rounds["fleetctl"][0]  # the plot's: round 1
    assert [len(r) for r in result["rounds"].values()] == [3, 3, 3]
    assert any(n.startswith("zenoh-best, round 3: 1: pose p50 1.70") for n in result["notes"])
    # One round: the criterion is that round's, named as before.
    alone = peeranalysis.fanout({v: rs[:1] for v, rs in rounds.items()})
    names = [c["name"] for c in alone["criteria"]]
    assert names == ["fleetctl / zenoh's best p50 at 1 consumer(s) (fewest)",
                     "fleetctl / zenoh's best p50 at 16 consumer(s) (most)"]
    assert [c["ok"] for c in alone["criteria"]] == [False, True]
