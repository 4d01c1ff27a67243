"""Pure analysis of the fleet scenarios: samples in, a report result dict out.

Result dicts follow :mod:`fleetctl.e2e.report` (``name``, ``status``, ``criteria``,
``notes``, ``plots``). Times in plots are seconds from the scenario's start.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from fleetctl.e2e.metrics import LatencyStats, by_topic, check_order, recovery_s
from fleetctl.e2e.samples import Sample

NO_DROP_DRAIN_S = 10.0  # how long after the load stops no_drop messages may still arrive


def crit(name: str, value: float, bound: float, ok: bool) -> dict[str, Any]:
    """One pass criterion row."""
    return {"name": name, "value": value, "bound": bound, "ok": bool(ok)}


def status_of(criteria: Sequence[dict[str, Any]]) -> str:
    """``pass`` when every criterion holds."""
    return "pass" if criteria and all(c["ok"] for c in criteria) else "fail"


def latency_line(samples: Sequence[Sample], t0_ns: int) -> list[list[float]]:
    """``[xs, ys]``: publish time (s from *t0_ns*) and latency (ms), in publish order."""
    ordered = sorted(samples, key=lambda s: s.publish_time_ns)
    return [[round((s.publish_time_ns - t0_ns) / 1e9, 4) for s in ordered],
            [round(s.latency_ms, 3) for s in ordered]]


def stats_dict(samples: Sequence[Sample]) -> dict[str, float]:
    """:class:`LatencyStats` as a JSON-ready dict."""
    st = LatencyStats.of(samples)
    return {"count": st.count, "p50_ms": st.p50_ms, "p90_ms": st.p90_ms, "p99_ms": st.p99_ms,
            "max_ms": st.max_ms}


def recovery_of(samples: Sequence[Sample], topics: Sequence[str], cut_ns: int,
                restore_ns: int) -> dict[str, float]:
    """Recovery time (s) per droppable topic (``inf``: not back by the end of the run)."""
    grouped = by_topic(samples)
    return {t: recovery_s(grouped.get(t, []), cut_ns, restore_ns) for t in topics}


def expected_no_drop(samples: Sequence[Sample], published: Mapping[str, int]) -> list[int]:
    """Sequence numbers a no_drop topic owes: from the first received to the last published.

    Messages published before the client's local subscription matched never reached the
    link, so they are not counted against it.
    """
    if not samples:
        return list(range(published["first_seq"], published["last_seq"] + 1))
    first = min(s.seq for s in samples)
    return list(range(first, published["last_seq"] + 1))


def dropout(
    variants: Mapping[str, Sequence[Sample]], published: Mapping[str, Mapping[str, Any]],
    droppable: Sequence[str], no_drop_topic: str, marks: Mapping[str, Mapping[str, int]],
) -> dict[str, Any]:
    """Dropout result: recovery per variant, no_drop delivery, ratio to the baseline.

    Args:
        variants: Samples of ``fleetctl`` and ``baseline`` (every topic no_drop).
        published: Per variant, what the load publisher published per topic.
        droppable: Topics whose latency recovery is measured.
        no_drop_topic: The event topic that must arrive whole and in order.
        marks: Per variant ``{"t0", "cut", "restore"}`` in ns since the epoch.
    """
    rec = {v: recovery_of(variants[v], droppable, marks[v]["cut"], marks[v]["restore"])
           for v in variants}
    worst = {v: max(r.values()) for v, r in rec.items()}
    events = [s for s in variants["fleetctl"] if s.topic == no_drop_topic]
    order = check_order(events, expected_no_drop(events, published["fleetctl"][no_drop_topic]))
    ratio = worst["baseline"] / worst["fleetctl"] if worst["fleetctl"] > 0 else math.inf
    criteria = [
        crit("recovery_s (worst droppable topic)", worst["fleetctl"], 1.0,
             worst["fleetctl"] <= 1.0),
        crit("baseline_recovery_s / recovery_s", ratio, 5.0, ratio >= 5.0),
        crit("no_drop events missing", order.missing, 0, order.missing == 0),
        crit("no_drop events out of order or duplicated",
             order.out_of_order + order.duplicates, 0,
             order.out_of_order == 0 and order.duplicates == 0),
    ]
    notes = [f"{v}: recovery per topic (s): "
             + ", ".join(f"{t} {x:.3f}" for t, x in r.items()) for v, r in rec.items()]
    if math.isinf(worst["baseline"]):
        notes.append("baseline latency was not back by the end of the run: the ratio is a "
                     "lower bound (inf)")
    notes.append(f"no_drop events: received {order.received}, missing {order.missing}, "
                 f"out of order {order.out_of_order}, duplicates {order.duplicates}")
    plots = []
    for v, samples in variants.items():
        t0 = marks[v]["t0"]
        span = [(marks[v]["cut"] - t0) / 1e9, (marks[v]["restore"] - t0) / 1e9, "link cut"]
        plots.append({
            "title": f"dropout: latency over time ({v})", "xlabel": "publish time (s)",
            "ylabel": "latency (ms)", "logy": True, "marker": ".", "style": "",
            "spans": [span],
            "lines": {t: latency_line(ss, t0) for t, ss in by_topic(samples).items()},
        })
    return {"name": "dropout", "status": status_of(criteria), "criteria": criteria,
            "notes": notes, "plots": plots,
            "stats": {v: {t: stats_dict(ss) for t, ss in by_topic(s).items()}
                      for v, s in variants.items()},
            "recovery_s": rec}


def priority(variants: Mapping[str, Sequence[Sample]], high: str, low: str,
             t0_ns: Mapping[str, int]) -> dict[str, Any]:
    """Priority result: the high-priority topic's p99 (fleetctl) under 15 ms."""
    stats = {v: {t: stats_dict(ss) for t, ss in by_topic(s).items()}
             for v, s in variants.items()}
    p99 = stats["fleetctl"].get(high, {}).get("p99_ms", math.nan)
    criteria = [crit("high-priority p99_ms", p99, 15.0, p99 < 15.0)]
    notes = [f"{v}: " + "; ".join(f"{t} p50 {st['p50_ms']:.1f} ms p99 {st['p99_ms']:.1f} ms "
                                  f"(n={st['count']})" for t, st in s.items())
             for v, s in stats.items()]
    plots = [{
        "title": f"priority: latency over time ({v})", "xlabel": "publish time (s)",
        "ylabel": "latency (ms)", "logy": True, "marker": ".", "style": "",
        "lines": {t: latency_line(ss, t0_ns[v]) for t, ss in by_topic(s).items()},
    } for v, s in variants.items()]
    return {"name": "priority", "status": status_of(criteria), "criteria": criteria,
            "notes": notes, "plots": plots, "stats": stats, "topics": [high, low]}


def multi_consumer(steps: Mapping[str, Sequence[Mapping[str, Any]]]) -> dict[str, Any]:
    """Multi-consumer result from per-step summaries.

    Args:
        steps: Per variant (``fleetctl``, ``dds``) a list of
            ``{"consumers", "uplink_bit_s", "p50_ms", "p99_ms", "received_per_consumer_hz"}``.
    """
    fleet = sorted(steps["fleetctl"], key=lambda s: s["consumers"])
    first, last = fleet[0], fleet[-1]
    rates = [s["uplink_bit_s"] for s in fleet]
    flat = max(rates) / min(rates) if min(rates) > 0 else math.inf
    lat_ratio = last["p50_ms"] / first["p50_ms"] if first["p50_ms"] > 0 else math.inf
    criteria = [
        crit("uplink max/min over consumer counts", flat, 1.1, flat <= 1.1),
        crit(f"p50 latency {last['consumers']} / {first['consumers']} consumers", lat_ratio,
             1.25, lat_ratio <= 1.25),
    ]
    notes = [f"{v}: " + "; ".join(
        f"{s['consumers']}: uplink {s['uplink_bit_s'] / 1e6:.2f} Mbit/s, p50 {s['p50_ms']:.1f} "
        f"ms, p99 {s['p99_ms']:.1f} ms, {s['received_per_consumer_hz']:.2f} msg/s each"
        for s in sorted(vs, key=lambda s: s["consumers"])) for v, vs in steps.items()]

    def line(key: str, scale: float = 1.0) -> dict[str, list[list[float]]]:
        return {v: [[s["consumers"] for s in vs], [s[key] / scale for s in vs]]
                for v, vs in steps.items() if vs}

    plots = [
        {"title": "multi-consumer: latency vs consumers (p50)", "xlabel": "consumers",
         "ylabel": "latency (ms)", "marker": "o", "logy": True, "lines": line("p50_ms")},
        {"title": "multi-consumer: robot uplink vs consumers", "xlabel": "consumers",
         "ylabel": "uplink (Mbit/s)", "marker": "o", "lines": line("uplink_bit_s", 1e6)},
        {"title": "multi-consumer: messages received per consumer", "xlabel": "consumers",
         "ylabel": "msg/s", "marker": "o", "lines": line("received_per_consumer_hz")},
    ]
    return {"name": "multi-consumer", "status": status_of(criteria), "criteria": criteria,
            "notes": notes, "plots": plots, "steps": {k: list(v) for k, v in steps.items()}}


def step_summary(samples: Sequence[Sample], consumers: int, uplink_bytes: int,
                 seconds: float) -> dict[str, Any]:
    """One multi-consumer step: uplink rate and latency of the messages received in it."""
    st = LatencyStats.of(samples)
    return {"consumers": consumers, "uplink_bit_s": uplink_bytes * 8 / seconds,
            "p50_ms": st.p50_ms, "p99_ms": st.p99_ms,
            "received_per_consumer_hz": len(samples) / consumers / seconds}


def ramp(variants: Mapping[str, Sequence[Sample]], high: str, t0_ns: Mapping[str, int],
         schedule: Mapping[str, Sequence[tuple[float, float]]],
         bound_ms: float) -> dict[str, Any]:
    """Ramp result: per-topic latency; the high-priority topic's p99 stays under *bound_ms*.

    Args:
        variants: Samples of ``fleetctl`` and ``baseline`` (every topic no_drop).
        high: The high-priority topic.
        t0_ns: Per variant, when the ramp started (ns since the epoch).
        schedule: Per variant, ``(seconds from t0, Mbit/s)`` of every rate change.
        bound_ms: The bound on the high-priority p99 (ms).
    """
    stats = {v: {t: stats_dict(ss) for t, ss in by_topic(s).items()}
             for v, s in variants.items()}
    p99 = stats["fleetctl"].get(high, {}).get("p99_ms", math.nan)
    criteria = [crit("high-priority p99_ms during the ramp", p99, bound_ms, p99 < bound_ms)]
    notes = [f"{v}: " + "; ".join(f"{t} p50 {st['p50_ms']:.1f} ms p99 {st['p99_ms']:.1f} ms "
                                  f"(n={st['count']})" for t, st in s.items())
             for v, s in stats.items()]
    plots = []
    for v, samples in variants.items():
        lines = {t: latency_line(ss, t0_ns[v]) for t, ss in by_topic(samples).items()}
        xs = [x for x, _ in schedule[v]]
        lines["link (Mbit/s)"] = [xs, [r for _, r in schedule[v]]]
        plots.append({"title": f"ramp 100 -> 4 Mbit/s: latency over time ({v})",
                      "xlabel": "publish time (s)", "ylabel": "latency (ms) / link (Mbit/s)",
                      "logy": True, "marker": ".", "style": "", "lines": lines})
    return {"name": "ramp", "status": status_of(criteria), "criteria": criteria,
            "notes": notes, "plots": plots, "stats": stats}
