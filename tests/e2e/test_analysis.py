"""Unit tests of the fleet scenarios' analysis (synthetic samples)."""

from __future__ import annotations

import math

import pytest

from fleetctl.e2e import analysis
from fleetctl.e2e.samples import Sample

S = 1_000_000_000


def _s(topic: str, t_s: float, latency_ms: float, seq: int = 0) -> Sample:
    recv = int(t_s * S)
    return Sample(topic, seq, recv - int(latency_ms * 1e6), recv, 100)


def _variant(backlog_s: float) -> list[Sample]:
    """10 Hz scan, 3 ms; cut 5-10 s; a backlog draining for *backlog_s*; events in order."""
    out = [_s("/r/scan", i / 10, 3.0) for i in range(50)]
    drain = int(backlog_s * 10)
    out += [_s("/r/scan", 10 + i / 10, 5000 - 5000 * i / max(drain, 1)) for i in range(drain)]
    out += [_s("/r/scan", 10 + backlog_s + i / 10, 3.0) for i in range(30)]
    out += [_s("/r/events", i / 10, 3.0, seq=i + 1) for i in range(50)]
    return out


MARKS = {"t0": 0, "cut": 5 * S, "restore": 10 * S}
PUBLISHED = {"/r/events": {"first_seq": 1, "last_seq": 50, "count": 50}}


def test_dropout_passes_when_fast_and_complete() -> None:
    res = analysis.dropout({"fleetctl": _variant(0.0), "baseline": _variant(4.0)},
                           {"fleetctl": PUBLISHED, "baseline": PUBLISHED}, ["/r/scan"],
                           "/r/events", {"fleetctl": MARKS, "baseline": MARKS})
    assert res["status"] == "pass", res["criteria"]
    assert res["recovery_s"]["fleetctl"]["/r/scan"] == pytest.approx(0.0)
    assert len(res["plots"]) == 2


def test_dropout_fails_on_a_missing_event_and_slow_recovery() -> None:
    fleet = [s for s in _variant(2.0) if not (s.topic == "/r/events" and s.seq == 20)]
    res = analysis.dropout({"fleetctl": fleet, "baseline": _variant(4.0)},
                           {"fleetctl": PUBLISHED, "baseline": PUBLISHED}, ["/r/scan"],
                           "/r/events", {"fleetctl": MARKS, "baseline": MARKS})
    failed = {c["name"] for c in res["criteria"] if not c["ok"]}
    assert failed == {"recovery_s (worst droppable topic)", "baseline_recovery_s / recovery_s",
                      "no_drop events missing"}


def test_priority_bound_is_on_the_high_topic_p99() -> None:
    fast = [_s("/r/high", i / 50, 5.0) for i in range(100)] + [_s("/r/low", 1, 300.0)]
    slow = [_s("/r/high", i / 50, 5.0 if i % 10 else 40.0) for i in range(100)]
    res = analysis.priority({"fleetctl": fast, "baseline": slow}, "/r/high", "/r/low",
                            {"fleetctl": 0, "baseline": 0})
    assert res["status"] == "pass"
    res = analysis.priority({"fleetctl": slow, "baseline": fast}, "/r/high", "/r/low",
                            {"fleetctl": 0, "baseline": 0})
    assert res["status"] == "fail"


def _steps(rates: list[float], lat: list[float]) -> list[dict[str, float]]:
    counts = (1, 2, 4, 8, 16)
    return [{"consumers": n, "uplink_bit_s": r, "p50_ms": lt, "p99_ms": lt * 2,
             "received_per_consumer_hz": 5.0}
            for n, r, lt in zip(counts, rates, lat, strict=True)]


def test_multi_consumer_flat_uplink_and_latency() -> None:
    ok = analysis.multi_consumer({"fleetctl": _steps([6e6] * 5, [50, 51, 52, 55, 60]),
                                  "dds": _steps([6e6, 12e6, 12e6, 12e6, 12e6],
                                                [50, 500, 900, 2000, 4000])})
    assert ok["status"] == "pass"
    bad = analysis.multi_consumer({"fleetctl": _steps([6e6, 6e6, 6e6, 6e6, 9e6],
                                                      [50, 50, 50, 50, 80])})
    assert [c["ok"] for c in bad["criteria"]] == [False, False]


def test_step_summary_rates() -> None:
    samples = [_s("/r/p", i / 5, 20.0) for i in range(20)]
    st = analysis.step_summary(samples, 2, 3_000_000, 2.0)
    assert st["uplink_bit_s"] == pytest.approx(12e6)
    assert st["received_per_consumer_hz"] == pytest.approx(5.0)
    assert st["p50_ms"] == pytest.approx(20.0)


def test_ramp_bound() -> None:
    fleet = [_s("/r/pose", i / 10, 10.0) for i in range(150)]
    base = [_s("/r/pose", i / 10, 10.0 * i) for i in range(150)]
    res = analysis.ramp({"fleetctl": fleet, "baseline": base}, "/r/pose",
                        {"fleetctl": 0, "baseline": 0},
                        {"fleetctl": [(0.0, 100.0)], "baseline": [(0.0, 100.0)]}, 100.0)
    assert res["status"] == "pass"
    assert math.isclose(res["stats"]["baseline"]["/r/pose"]["max_ms"], 1490.0)
