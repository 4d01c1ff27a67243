"""The ``peer-large`` scenario: a camera's JPEGs beside a pose on a slow link, fleetctl
against zenoh (issue 19, fewer bytes than the strongest peer, for large messages too).

Load (profile ``peer-large``): a 100 KB CompressedImage at 3 Hz (random bytes: as
compressible as a JPEG) and a PoseStamped at 20 Hz, on a 4 Mbit/s link (60 % of it), no
cut. The three variants of the ``peer`` scenario, placed alike
(:mod:`fleetctl.e2e.peerscenario`), one after the other, each for ``max(6, D)`` s after
its consumer received both topics. Per variant: the uplink (router tx towards the server
network over the window) per byte of CDR delivered, every overhead included (framing,
fragment metadata, deflate, TCP, WireGuard, IP); the pose's latency while the images flow
(what a large message costs a small urgent one: fleetctl interleaves 1 KiB fragments by
priority, zenoh sends a message's fragments in its batches); the image's latency and the
share of published messages delivered.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from fleetctl.deploy.shaping import Capabilities
from fleetctl.e2e import profiles, robotview
from fleetctl.e2e.analysis import crit, latency_line, status_of
from fleetctl.e2e.fleetrun import FleetRun
from fleetctl.e2e.metrics import LatencyStats, by_topic
from fleetctl.e2e.peeranalysis import mean_bytes
from fleetctl.e2e.samples import Sample
from fleetctl.e2e.topology import SERVER_SIDE
from fleetctl.errors import FleetError

Progress = Callable[[str], None]
LINK_MBIT = 4.0
MIN_WINDOW_S = 6.0
IMAGE_WAIT_S = 10.0  # after the pose flows: a few image periods, and the first's transfer
POSE = "/robot1/pose"
IMAGE_BYTES = 100_000


@dataclass(frozen=True)
class LargeRun:
    """One variant's window.

    Attributes:
        samples: The messages published in the window that its consumer received.
        seconds: The window's length.
        uplink_bit_s: Router tx towards the server network over the window.
        published_hz: The load's rate per wire topic.
    """

    samples: Sequence[Sample]
    seconds: float
    uplink_bit_s: float
    published_hz: Mapping[str, float]


def run_peer_large(fr: FleetRun, caps: Capabilities, duration_s: float,
                   progress: Progress) -> dict[str, Any]:
    """fleetctl, zenoh with the bridge's defaults, zenoh at its best: same load, same link."""
    from fleetctl.e2e.peerscenario import ZENOH_VARIANTS, _Run
    from fleetctl.e2e.scenarios import Link

    p = profiles.profile("peer-large")
    link = Link(fr, caps)
    seconds = max(MIN_WINDOW_S, duration_s)
    runs: dict[str, LargeRun] = {}
    views: list[str] = []
    for variant in ("fleetctl", *ZENOH_VARIANTS):
        link.rate(LINK_MBIT)
        with _Run(fr, variant, p, consumers=0, scenario="large") as run:
            tag = f"large-{variant}-consumer"
            consumers = run.start_consumers(tag, 1)
            try:
                fr.wait_flowing(tag, [POSE], [f"{tag}-0"])
                # A variant that never delivers an image is a result, not a run that
                # failed: zenoh at its best settings (congestion control Drop, one-batch
                # queues, 8 KiB socket buffers) dropped every 100 KB image at 4 Mbit/s.
                with contextlib.suppress(FleetError):
                    fr.wait_flowing(tag, run.topics, [f"{tag}-0"], IMAGE_WAIT_S)
                progress(f"peer-large/{variant}: {seconds:g} s at {LINK_MBIT:g} Mbit/s")
                before = run.robot_stats()
                window = fr.topo.count_tx(fr.topo.router, fr.topo.router_devs[SERVER_SIDE],
                                          seconds)
                if variant == "fleetctl":
                    views.append(robotview.window_note(
                        "fleetctl robot in the window", before, run.robot_stats()))
                run.stop()
            finally:
                fr.remove(consumers)
            samples = fr.samples(tag)
        # Messages published in the window (their latency may end after it).
        inside = [s for s in samples
                  if window.start_ns <= s.publish_time_ns <= window.end_ns]
        runs[variant] = LargeRun(inside, window.seconds, window.tx_bytes * 8 / window.seconds,
                                 {t.remote_topic: t.rate_hz for t in p.topics})
    link.clear()
    result = peer_large(runs)
    result["notes"].extend(views)
    load = ", ".join(f"{t.remote_topic} at {t.rate_hz:g} Hz" for t in p.topics)
    result["notes"].insert(0, (
        f"load: {load} (the image {IMAGE_BYTES:,} B of random bytes); {LINK_MBIT:g} Mbit/s "
        f"both ways; {seconds:g} s per variant after its consumer received both topics; "
        "consumers and zenoh router placed as in peer"))
    return result


def cdr_bytes(runs: Mapping[str, LargeRun]) -> dict[str, float]:
    """Mean CDR size per topic: what a zenoh consumer receives is the CDR itself; without
    a zenoh variant, fleetctl's frame size (a few dozen bytes more)."""
    for variant, run in runs.items():
        if variant != "fleetctl" and run.samples:
            return mean_bytes(run.samples)
    return mean_bytes(runs["fleetctl"].samples) if "fleetctl" in runs else {}


def variant_figures(run: LargeRun, cdr: Mapping[str, float]) -> dict[str, Any]:
    """Per topic latency and delivery, and the uplink per CDR byte delivered."""
    topics = by_topic(run.samples)
    delivered_Bps = sum(len(ss) / run.seconds * cdr.get(t, 0.0) for t, ss in topics.items())
    figures: dict[str, Any] = {
        "uplink_Mbit_s": run.uplink_bit_s / 1e6,
        "wire_per_cdr_byte": (run.uplink_bit_s / 8 / delivered_Bps if delivered_Bps > 0
                              else math.inf),
        "topics": {}}
    for topic, hz in run.published_hz.items():
        ss = topics.get(topic, [])
        stats = LatencyStats.of(ss)
        figures["topics"][topic] = {
            "p50_ms": stats.p50_ms, "p99_ms": stats.p99_ms,
            "delivered": len(ss) / (hz * run.seconds) if hz > 0 else math.nan}
    return figures


def peer_large(runs: Mapping[str, LargeRun]) -> dict[str, Any]:
    """The scenario's result: fleetctl against the better zenoh variant on bytes and on
    the pose's p99."""
    cdr = cdr_bytes(runs)
    figs = {v: variant_figures(r, cdr) for v, r in runs.items()}
    ours = figs["fleetctl"]
    zenohs = {v: f for v, f in figs.items() if v != "fleetctl"}
    fewest = min((f["wire_per_cdr_byte"] for f in zenohs.values()), default=math.nan)
    lowest = min((f["topics"].get(POSE, {}).get("p99_ms", math.nan)
                  for f in zenohs.values()), default=math.nan)
    ratio = ours["wire_per_cdr_byte"] / fewest if fewest > 0 else math.inf
    pose = ours["topics"].get(POSE, {}).get("p99_ms", math.nan)
    criteria = [
        crit("fleetctl / zenoh's fewest uplink bytes per CDR byte delivered", ratio, 1.0,
             ratio <= 1.0),
        crit("fleetctl pose p99 while the images flow / zenoh's lowest", pose / lowest,
             1.0, pose <= lowest),
    ]
    notes = [f"{v}: uplink {f['uplink_Mbit_s']:.2f} Mbit/s, {f['wire_per_cdr_byte']:.3f} "
             "bytes on the uplink per CDR byte delivered; " + "; ".join(
                 f"{t.rsplit('/', 1)[-1]} p50 {x['p50_ms']:.1f} p99 {x['p99_ms']:.1f} ms, "
                 f"{x['delivered']:.0%} delivered" for t, x in sorted(f["topics"].items()))
             for v, f in figs.items()]
    notes.append("CDR per message: " + ", ".join(
        f"{t.rsplit('/', 1)[-1]} {b:,.0f} B" for t, b in sorted(cdr.items())))
    lines = {}
    for variant, run in runs.items():
        pose_samples = by_topic(run.samples).get(POSE, [])
        t0 = min((s.publish_time_ns for s in run.samples), default=0)
        lines[f"{variant} pose"] = latency_line(pose_samples, t0)
    plots = [{"title": "peer-large: the pose's latency while the images flow",
              "xlabel": "time in the window (s)", "ylabel": "latency (ms)",
              "logy": True, "lines": lines}]
    return {"name": "peer-large", "status": status_of(criteria), "criteria": criteria,
            "notes": notes, "plots": plots, "variants": figs}
