"""Unit tests of the e2e analysis and report (pure; synthetic samples)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from fleetctl.e2e import report, samples
from fleetctl.e2e.metrics import (
    LatencyStats,
    check_order,
    publish_period_ns,
    recovery_limit_s,
    recovery_s,
    throughput_bit_s,
)
from fleetctl.e2e.samples import Sample
from fleetctl.errors import FleetError

S = 1_000_000_000


def _s(t_s: float, latency_ms: float, seq: int = 0, size: int = 100) -> Sample:
    recv = int(t_s * S)
    return Sample("/r/scan", seq, recv - int(latency_ms * 1e6), recv, size)


def _run(after_restore: list[float]) -> list[Sample]:
    """10 ms latency at 10 Hz for 5 s, cut 5-10 s, then *after_restore* latencies."""
    pre = [_s(i / 10, 10.0) for i in range(50)]
    post = [_s(10 + i / 10, lat) for i, lat in enumerate(after_restore)]
    return pre + post


def test_recovery_is_immediate_when_latency_returns_at_once() -> None:
    run = _run([15.0] * 30)
    assert recovery_s(run, 5 * S, 10 * S) == pytest.approx(0.0)


def test_recovery_waits_for_a_backlog_to_drain() -> None:
    # 2.5 s of backlog (latency falling from 5 s), then normal.
    run = _run([5000 - 200 * i for i in range(25)] + [12.0] * 30)
    assert recovery_s(run, 5 * S, 10 * S) == pytest.approx(2.5)


def test_recovery_needs_the_hold_window_median_under_the_bound() -> None:
    # Under the bound once, then mostly over it for a second: not recovered there.
    run = _run([12.0] + [900.0] * 12 + [12.0] * 30)
    assert recovery_s(run, 5 * S, 10 * S) == pytest.approx(1.3)
    assert math.isinf(recovery_s(_run([500.0] * 30), 5 * S, 10 * S))


def test_isolated_spikes_like_before_the_cut_do_not_delay_recovery() -> None:
    run = _run([12.0, 12.0, 900.0] + [12.0] * 30)
    assert recovery_s(run, 5 * S, 10 * S) == pytest.approx(0.0)
    assert math.isinf(recovery_s([], 5 * S, 10 * S))


def _timer(phase_s: float, lost: set[int]) -> list[Sample]:
    """A 10 Hz topic published at phase_s + k/10 with 3 ms latency, cut 5-10 s; the
    messages numbered in *lost* never arrive."""
    out = []
    for seq in range(150):
        pub = phase_s + seq / 10
        if 5 <= pub < 10 or seq in lost:
            continue
        out.append(Sample("/r/scan", seq, int(pub * S), int(pub * S) + 3_000_000, 100))
    return out


def test_the_period_comes_from_the_stamps_whatever_was_lost() -> None:
    assert publish_period_ns(_timer(0.0, {3, 4, 20})) == pytest.approx(0.1 * S)
    assert math.isnan(publish_period_ns(_timer(0.0, set())[:1]))


def test_the_recovery_limit_is_the_next_publish_after_the_restore_plus_the_floor() -> None:
    # Published at x.03: the first publish after the restore at 10 s is 10.03 s.
    assert recovery_limit_s(_timer(0.03, set()), 5 * S, 10 * S) == pytest.approx(0.033)
    # The stack lost the first three after the restore: the timer still says 10.03 s.
    lost = {100, 101, 102}
    assert recovery_limit_s(_timer(0.03, lost), 5 * S, 10 * S) == pytest.approx(0.033)
    # Published at x.09: 90 ms to wait whatever the stack does.
    assert recovery_limit_s(_timer(0.09, set()), 5 * S, 10 * S) == pytest.approx(0.093)
    assert math.isnan(recovery_limit_s(_timer(0.0, set())[:40], 5 * S, 10 * S))


def test_order_check_counts_missing_duplicates_inversions() -> None:
    good = [_s(i, 1, seq=i) for i in range(5)]
    assert check_order(good, range(5)).ok
    bad = [_s(0, 1, 0), _s(1, 1, 2), _s(2, 1, 1), _s(3, 1, 2)]
    res = check_order(bad, range(5))
    assert (res.missing, res.out_of_order, res.duplicates, res.ok) == (2, 1, 1, False)


def test_latency_stats_and_throughput() -> None:
    st = LatencyStats.of([_s(i / 100, float(i)) for i in range(1, 101)])
    assert st.count == 100 and st.p50_ms == pytest.approx(50.5) and st.max_ms == 100.0
    assert math.isnan(LatencyStats.of([]).p99_ms)
    assert throughput_bit_s([_s(0, 1, size=1000), _s(1, 1, size=1000)]) == 16000.0


def test_samples_round_trip_and_bad_lines_are_named() -> None:
    items = [_s(1, 2, seq=3)]
    assert list(samples.load(samples.dump(items))) == items
    with pytest.raises(FleetError, match=r"consumer\.jsonl:2"):
        list(samples.load(samples.dump(items) + "{\"topic\": 1}\n", "consumer.jsonl"))


def test_report_writes_json_markdown_and_png(tmp_path: Path) -> None:
    result = {
        "name": "dropout", "status": "fail",
        "criteria": [{"name": "recovery_s", "value": math.inf, "bound": 1.0, "ok": False}],
        "notes": ["cut with bfifo-limit-0"],
        "plots": [{"title": "t", "xlabel": "s", "ylabel": "ms", "spans": [[1, 2, "cut"]],
                   "lines": {"scan": [[0, 1, 2, 3], [5, 5, 9, 5]]}}],
    }
    md = report.write(tmp_path, {"tc": "netem: no"}, [result])
    doc = json.loads((tmp_path / "report.json").read_text())
    assert doc["ok"] is False and doc["scenarios"][0]["name"] == "dropout"
    text = md.read_text()
    assert "| dropout | fail | recovery_s | inf | 1 | False |" in text
    assert (tmp_path / "dropout-0.png").read_bytes()[:4] == b"\x89PNG"
    assert not report.overall_ok([]) and report.overall_ok([{"status": "pass"}])
