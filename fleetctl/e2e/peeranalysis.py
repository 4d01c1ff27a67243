"""Pure analysis of the ``peer`` scenario: fleetctl against zenoh, trial by trial."""

from __future__ import annotations

import math
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from fleetctl.e2e.analysis import crit, latency_line, status_of
from fleetctl.e2e.metrics import LatencyStats, by_topic, recovery_limit_s, recovery_s
from fleetctl.e2e.samples import Sample

RECOVERY_BAR_S = 0.1  # issue 19: every trial back within 0.1 s
ZENOH_FACTOR = 4.0  # ... and at least 4x sooner than zenoh at its best, trial by trial
UPLINK_BAR_BIT_S = 0.50e6


@dataclass(frozen=True)
class VariantRun:
    """What one variant's run gave.

    Attributes:
        samples: Every sample its consumer recorded.
        t0_ns: When its steady phase started.
        trials: ``(cut, restore, end)`` of each trial (ns since the epoch).
        uplink_bit_s: Router tx towards the server network in the steady window.
        published: What the load publisher published per wire topic.
        messages_per_s: The load's message rate (all topics), for the uplink bytes per
            message; 0 when unknown.
        floor_rounds_ms: The latency floor (p50) of each further round of steady phases
            (:func:`fleetctl.e2e.peerscenario.run_peer`: the variants alternating, each
            first in one round), beside this run's own.
    """

    samples: Sequence[Sample]
    t0_ns: int
    trials: Sequence[tuple[int, int, int]]
    uplink_bit_s: float
    published: Mapping[str, Mapping[str, int]]
    messages_per_s: float = 0.0
    floor_rounds_ms: Sequence[float] = ()


@dataclass(frozen=True)
class Trial:
    """One cut of one variant.

    Attributes:
        recovery_s: Per topic, seconds from the restore until latency is back.
        first_s: Seconds from the restore to the first message received after it.
        stale: Messages received after the restore that were published before it.
        limit_s: Per topic, the soonest any stack could have recovered
            (:func:`fleetctl.e2e.metrics.recovery_limit_s`: the topic's next publish after
            the restore plus its floor). A 10 Hz topic's is anywhere in 0-0.1 s.
        stale_before_s: How long before the restore the oldest stale message was
            published (0 without one): a backlog that waited out the cut is seconds old,
            a message published a millisecond before the restore mark is not, and the
            count alone does not tell them apart.
    """

    recovery_s: Mapping[str, float]
    first_s: float
    stale: int
    limit_s: Mapping[str, float] = field(default_factory=dict)
    stale_before_s: float = 0.0

    @property
    def worst_s(self) -> float:
        """The slowest topic's recovery."""
        return max(self.recovery_s.values()) if self.recovery_s else math.inf

    @property
    def past_limit_s(self) -> float:
        """The stack's own share: the worst topic's recovery beyond its limit (NaN when
        a limit is unknown)."""
        gaps = [r - self.limit_s.get(t, math.nan) for t, r in self.recovery_s.items()]
        return max(gaps) if gaps and not any(math.isnan(g) for g in gaps) else math.nan


def trials_of(run: VariantRun, topics: Sequence[str]) -> list[Trial]:
    """Each trial measured on the samples between the previous trial's end and its own,
    against the latency of the steady phase before the first cut (the trials follow each
    other without a steady phase in between)."""
    out = []
    first_cut = run.trials[0][0] if run.trials else run.t0_ns
    steady = [s for s in run.samples if run.t0_ns <= s.recv_time_ns < first_cut]
    start = run.t0_ns
    for cut, restore, end in run.trials:
        window = [s for s in run.samples if start <= s.recv_time_ns < end]
        grouped = by_topic([*steady, *(s for s in window if s.recv_time_ns >= cut)])
        rec = {t: recovery_s(grouped.get(t, []), cut, restore) for t in topics}
        limit = {t: recovery_limit_s(grouped.get(t, []), cut, restore) for t in topics}
        after = [s for s in window if s.recv_time_ns >= restore]
        first = (min(s.recv_time_ns for s in after) - restore) / 1e9 if after else math.inf
        stale = [restore - s.publish_time_ns for s in after if s.publish_time_ns < restore]
        out.append(Trial(rec, first, len(stale), limit, max(stale, default=0) / 1e9))
        start = end
    return out


def p50_before_ms(samples: Sequence[Sample], end_ns: float) -> float:
    """p50 latency of the samples received before *end_ns* (a steady phase's floor)."""
    return LatencyStats.of([s for s in samples if s.recv_time_ns < end_ns]).p50_ms


def floor_p50_ms(run: VariantRun) -> float:
    """p50 latency of every message received before the first cut (the latency floor)."""
    return p50_before_ms(run.samples, run.trials[0][0] if run.trials else math.inf)


def floor_rounds_ms(run: VariantRun) -> list[float]:
    """The latency floor of every round of *run*, its own first.

    Why rounds: the stacks run one after the other, and on a 2-core host the same code's
    floor moved 1.05-1.42x against zenoh's from one run to the next (docs/peers.md, "How
    much one run's floor says"): one p50 each compared the minutes the stacks ran in as
    much as the stacks. Rounds in which each stack runs first once, and the median of
    each (:func:`peer`), compare the stacks.
    """
    return [floor_p50_ms(run), *run.floor_rounds_ms]


def rounds_note(what: str, rounds: Mapping[str, Sequence[float]]) -> str:
    """Each variant's figure round by round and its median, and fleetctl's against the
    lowest zenoh in each round (*what* names the figure, in ms)."""
    parts = [f"{v} " + " / ".join(f"{x:.2f}" for x in xs)
             + f" (median {statistics.median(xs):.2f})" for v, xs in rounds.items()]
    note = f"{what} by round (ms; each round the variants one after the other, their " \
        "order rotated from round to round): " + "; ".join(parts)
    fleet = rounds.get("fleetctl", [])
    zenoh = [xs for v, xs in rounds.items() if v != "fleetctl"]
    if fleet and zenoh:
        ratios = [f / min(z) for f, *z in zip(fleet, *zenoh, strict=False) if min(z) > 0]
        note += "; fleetctl / lowest zenoh by round: " + ", ".join(f"{r:.2f}x" for r in ratios)
    return note


def peer(runs: Mapping[str, VariantRun], topics: Sequence[str]) -> dict[str, Any]:
    """The scenario's result: criteria, notes, plots (``fleetctl``, ``zenoh-*`` variants)."""
    trials = {v: trials_of(r, topics) for v, r in runs.items()}
    fleet = trials["fleetctl"]
    worst = max((t.worst_s for t in fleet), default=math.inf)
    stale = sum(t.stale for t in fleet)
    best = trials.get("zenoh-best", [])
    factors = [b.worst_s / f.worst_s if f.worst_s > 0 else math.inf
               for f, b in zip(fleet, best, strict=False)]
    factor = min(factors, default=math.nan)
    rounds = {v: floor_rounds_ms(r) for v, r in runs.items()}
    floors = {v: statistics.median(xs) for v, xs in rounds.items()}
    zenoh_floor = min((f for v, f in floors.items() if v != "fleetctl"), default=math.nan)
    uplink = runs["fleetctl"].uplink_bit_s
    criteria = [
        crit("fleetctl recovery, worst topic of the worst trial (s)", worst, RECOVERY_BAR_S,
             worst <= RECOVERY_BAR_S),
        crit("fleetctl stale messages after the restores", stale, 0, stale == 0),
        crit("zenoh-best / fleetctl recovery, worst trial", factor, ZENOH_FACTOR,
             factor >= ZENOH_FACTOR),
        crit("fleetctl steady uplink (Mbit/s)", uplink / 1e6, UPLINK_BAR_BIT_S / 1e6,
             uplink <= UPLINK_BAR_BIT_S),
        crit("fleetctl latency floor p50 / zenoh's best p50 (medians of the rounds)",
             floors["fleetctl"] / zenoh_floor
             if zenoh_floor > 0 else math.inf, 1.0, floors["fleetctl"] <= zenoh_floor),
    ]
    notes = []
    for v, ts in trials.items():
        cuts = [(rs - c) / 1e9 for c, rs, _ in runs[v].trials]
        per = "; ".join(
            f"trial {i + 1} (cut {cut:.1f} s): " + ", ".join(
                f"{t.rsplit('/', 1)[-1]} {x:.3f} (limit {tr.limit_s.get(t, math.nan):.3f})"
                for t, x in tr.recovery_s.items())
            + f" s, first message {tr.first_s:.3f} s, stale {tr.stale}"
            + (f" (published up to {tr.stale_before_s * 1e3:.1f} ms before the restore)"
               if tr.stale else "")
            for i, (tr, cut) in enumerate(zip(ts, cuts, strict=False)))
        notes.append(f"{v}: uplink {runs[v].uplink_bit_s / 1e6:.3f} Mbit/s, latency floor "
                     f"p50 {floors[v]:.2f} ms; {per}")
    notes.append(rounds_note("latency floor p50", rounds))
    notes.append(limit_note(trials))
    notes.append(bytes_note(runs))
    plots = []
    for v, r in runs.items():
        spans = [[(c - r.t0_ns) / 1e9, (rs - r.t0_ns) / 1e9, "link cut"]
                 for c, rs, _ in r.trials]
        plots.append({
            "title": f"peer: latency over time ({v})", "xlabel": "publish time (s)",
            "ylabel": "latency (ms)", "logy": True, "marker": ".", "style": "",
            "spans": spans,
            "lines": {t: latency_line(ss, r.t0_ns) for t, ss in by_topic(r.samples).items()},
        })
    return {"name": "peer", "status": status_of(criteria), "criteria": criteria,
            "notes": notes, "plots": plots,
            "trials": {v: [{"recovery_s": dict(t.recovery_s), "first_s": t.first_s,
                            "stale": t.stale, "stale_before_s": t.stale_before_s,
                            "limit_s": dict(t.limit_s),
                            "past_limit_s": t.past_limit_s} for t in ts]
                       for v, ts in trials.items()},
            "floor_p50_ms": floors,
            "uplink_bit_s": {v: r.uplink_bit_s for v, r in runs.items()}}


def limit_note(trials: Mapping[str, Sequence[Trial]]) -> str:
    """Each variant's recovery beyond the physical limit, per trial: what is left when the
    wait for the topic's next publish (a phase no stack controls) is taken out."""
    parts = []
    for v, ts in trials.items():
        gaps = [t.past_limit_s for t in ts]
        known = sorted(g for g in gaps if not math.isnan(g))
        if not known:
            continue
        parts.append(f"{v} {known[0]:.3f}-{known[-1]:.3f} s (median "
                     f"{known[len(known) // 2]:.3f}; per trial "
                     + ", ".join("?" if math.isnan(g) else f"{g:.3f}" for g in gaps) + ")")
    return ("recovery past the physical limit (the worst topic's recovery minus its next "
            "publish after the restore and its floor): " + ("; ".join(parts) or "unknown"))


def mean_bytes(samples: Sequence[Sample]) -> dict[str, float]:
    """Mean message size per topic as the consumer received it (a fleetctl frame with its
    metadata; a zenoh sample's payload, which is the CDR)."""
    return {t: sum(s.size_bytes for s in ss) / len(ss) for t, ss in by_topic(samples).items()}


def bytes_note(runs: Mapping[str, VariantRun]) -> str:
    """Bytes per message per topic: fleetctl's frame against the CDR zenoh carries; then
    what each variant's uplink cost per message, every overhead included (the uplink
    deflate, framing, TCP, WireGuard, IP, Ethernet)."""
    fleet = mean_bytes(runs["fleetctl"].samples)
    cdr = next((mean_bytes(r.samples) for v, r in runs.items() if v != "fleetctl"), {})
    parts = [f"{t} fleetctl {b:.0f}" + (f" (CDR {cdr[t]:.0f}, +{b - cdr[t]:.0f})"
                                        if t in cdr else "")
             for t, b in sorted(fleet.items())]
    note = "bytes per message (frame as relayed): " + "; ".join(parts)
    wire = [f"{v} {r.uplink_bit_s / 8 / r.messages_per_s:.0f}" for v, r in runs.items()
            if r.messages_per_s > 0]
    if wire:
        note += "; on the uplink, all overheads included: " + ", ".join(wire)
    return note


def fanout_step(samples: Sequence[Sample], consumers: int, seconds: float) -> dict[str, Any]:
    """One consumer count: p50/p99 per topic and messages per consumer per second."""
    per_topic = {t: {"p50_ms": LatencyStats.of(ss).p50_ms, "p99_ms": LatencyStats.of(ss).p99_ms}
                 for t, ss in by_topic(samples).items()}
    return {"consumers": consumers, "topics": per_topic,
            "received_per_consumer_hz": len(samples) / consumers / seconds}


def fanout(rounds: Mapping[str, Sequence[Sequence[Mapping[str, Any]]]]) -> dict[str, Any]:
    """fleetctl's p50 at the fewest and the most consumers, against zenoh's best.

    *rounds* holds, per variant, one sweep of the consumer counts (:func:`fanout_step`
    each) per round, its first round first. Each criterion compares the variants' medians
    over the rounds, for the reason the floor does (:func:`floor_rounds_ms`: the stacks
    run one after the other, and the one-consumer ratio of the same code read 1.06-1.37x
    from one run to the next); a step's p50 is that of its slower topic. The report's
    steps and plot are the first round's.
    """
    def p50(step: Mapping[str, Any]) -> float:
        return max((x["p50_ms"] for x in step["topics"].values()), default=math.nan)

    steps = {v: rs[0] for v, rs in rounds.items()}
    zenohs = [v for v in steps if v != "fleetctl"]
    criteria, round_notes = [], []
    for index, label in ((0, "fewest"), (-1, "most")):
        n = steps["fleetctl"][index]["consumers"]
        by_round = {v: [p50(sweep[index]) for sweep in rs] for v, rs in rounds.items()}
        medians = {v: statistics.median(xs) for v, xs in by_round.items()}
        ours = medians["fleetctl"]
        theirs = min((medians[v] for v in zenohs), default=math.nan)
        ratio = ours / theirs if theirs > 0 else math.inf
        name = f"fleetctl / zenoh's best p50 at {n} consumer(s) ({label})"
        if len(rounds["fleetctl"]) > 1:
            name += ", medians of the rounds"
        criteria.append(crit(name, ratio, 1.0, ratio <= 1.0))
        round_notes.append(rounds_note(f"fan-out p50 at {n} consumer(s), slower topic,",
                                       by_round))
    notes = [f"{v}" + (f", round {k + 1}" if len(rs) > 1 else "") + ": " + "; ".join(
        f"{s['consumers']}: " + ", ".join(
            f"{t.rsplit('/', 1)[-1]} p50 {x['p50_ms']:.2f} p99 {x['p99_ms']:.2f} ms"
            for t, x in sorted(s["topics"].items()))
        + f", {s['received_per_consumer_hz']:.1f} msg/s each" for s in vs)
        for v, rs in rounds.items() for k, vs in enumerate(rs)]
    lines = {f"{v} {t.rsplit('/', 1)[-1]}": [[s["consumers"] for s in vs],
                                              [s["topics"].get(t, {}).get("p50_ms", math.nan)
                                               for s in vs]]
             for v, vs in steps.items() for t in sorted(vs[0]["topics"])}
    plots = [{"title": "peer-fanout: p50 latency vs consumers (first round)",
              "xlabel": "consumers", "ylabel": "latency (ms)", "marker": "o", "logy": False,
              "lines": lines}]
    notes.extend(round_notes)
    return {"name": "peer-fanout", "status": status_of(criteria), "criteria": criteria,
            "notes": notes, "plots": plots, "steps": {k: list(v) for k, v in steps.items()},
            "rounds": {k: [list(sweep) for sweep in v] for k, v in rounds.items()}}
