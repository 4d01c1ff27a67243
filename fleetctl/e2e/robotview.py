"""The robot client's own view of its link over a measured window, for a scenario's notes.

Why: a latency p50 that reads high in one run and not in the next (docs/peers.md, "How much
one run's floor says") is easier to read beside what the robot measured in that window:
the link rate its scheduler holds, the longest frame it sends whole, how many frames each
topic's messages went as, and whether it deflated every message (the slow-link rule). On
2026-12-07 one fan-out run's robot read its 12 Mbit/s link as 4.3 Mbit/s on the wire at
connect and deflated everything for the whole run, the run whose scan p50 was the highest
of the day; only its log line said so.

The client writes a ``stats: {JSON}`` log line on SIGUSR1 (``fleetctl client``); a window's
view is the difference of two such snapshots (:func:`window_view`), formatted as one note
(:func:`view_note`; both at once: :func:`window_note`). Reading is best effort: a robot that
does not answer gives no view, and the note says so instead of failing the scenario.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from fleetctl.deploy.dockercli import Completed
from fleetctl.errors import FleetError
from fleetctl.waiting import wait_until

STATS_MARK = "stats: "
_POLL_S = 0.1


class _Containers(Protocol):
    """What is used of :class:`fleetctl.e2e.topology.Topology`."""

    def exec(self, container: str, argv: Sequence[str], *, user: str = ...) -> Completed: ...

    def logs(self, container: str) -> str: ...


@dataclass(frozen=True)
class TopicFrames:
    """One topic's messages and frames sent in the window."""

    messages: int
    frames: int


@dataclass(frozen=True)
class RobotView:
    """What the robot's link measured and did in a window.

    Attributes:
        link_rate_Bps: The scheduler's link rate at the window's end (frame bytes/s).
        whole_frame_bytes: The longest frame it sent unsplit then.
        window_bytes: Its in-flight window then.
        min_rtt_ms: Its smallest round trip in the RTT filter then (None before any).
        deflate_all: Whether it deflated every message (the slow-link rule) at the end.
        deflate_switches: Times that rule switched during the window.
        wire_share: Wire bytes per frame byte over its recent traffic.
        topics: Per topic, what it sent in the window.
    """

    link_rate_Bps: float
    whole_frame_bytes: int
    window_bytes: int
    min_rtt_ms: float | None
    deflate_all: bool
    deflate_switches: int
    wire_share: float
    topics: Mapping[str, TopicFrames]


def read_stats(containers: _Containers, container: str, timeout_s: float = 10.0) -> (
        dict[str, Any] | None):
    """Ask the robot client in *container* for its stats (SIGUSR1) and return the
    snapshot it logs; None when it wrote none within *timeout_s* or the line is not
    JSON."""
    before = containers.logs(container).count(STATS_MARK)
    res = containers.exec(container, ["pkill", "-USR1", "-f", "fleetctl client"])
    if res.returncode != 0:  # no client process to signal (it exited)
        return None
    text = ""

    def written() -> bool:
        nonlocal text
        text = containers.logs(container)
        return text.count(STATS_MARK) > before

    try:
        wait_until(written, timeout_s, _POLL_S, describe="the robot's stats line")
    except FleetError:  # a robot that does not answer leaves the note without its view
        return None
    line = [ln for ln in text.splitlines() if STATS_MARK in ln][-1]
    try:
        snapshot = json.loads(line.split(STATS_MARK, 1)[1])
    except ValueError:
        return None
    return snapshot if isinstance(snapshot, dict) else None


def window_view(start: Mapping[str, Any], end: Mapping[str, Any]) -> RobotView:
    """The window between two snapshots: its sends per topic (differences), the link's
    limits at its end."""
    begun = start.get("topics", {})
    topics = {}
    for name, counts in end.get("topics", {}).items():
        before = begun.get(name, {})
        topics[name] = TopicFrames(
            int(counts.get("sent", 0)) - int(before.get("sent", 0)),
            int(counts.get("sent_frames", 0)) - int(before.get("sent_frames", 0)))
    deflate = end.get("uplink_deflate") or {}
    deflate_before = start.get("uplink_deflate") or {}
    return RobotView(
        link_rate_Bps=float(end.get("link_rate_Bps") or 0.0),
        whole_frame_bytes=int(end.get("whole_frame_bytes") or 0),
        window_bytes=int(end.get("window_bytes") or 0),
        min_rtt_ms=end.get("min_rtt_ms"),
        deflate_all=bool(deflate.get("all_messages", False)),
        deflate_switches=int(deflate.get("switches", 0)) - int(deflate_before.get("switches", 0)),
        wire_share=float(deflate.get("wire_share", 1.0)),
        topics=topics)


def view_note(label: str, view: RobotView | None) -> str:
    """One note line: *label*, then the robot's view (or that it gave none)."""
    if view is None:
        return f"{label}: the robot client gave no stats (SIGUSR1) for this window"
    rtt = "none" if view.min_rtt_ms is None else f"{view.min_rtt_ms:.2f} ms"
    sends = ", ".join(
        f"{name} {t.messages} messages in {t.frames} frames"
        for name, t in sorted(view.topics.items()) if t.messages or t.frames)
    rule = (f"deflating every message (slow-link rule), wire share {view.wire_share:.2f}"
            if view.deflate_all else "deflating small messages only")
    switched = f", {view.deflate_switches} switch(es) in the window" if view.deflate_switches \
        else ""
    return (f"{label}: link rate {view.link_rate_Bps * 8e-6:.1f} Mbit/s of frame bytes, "
            f"frames up to {view.whole_frame_bytes} B sent whole, window "
            f"{view.window_bytes} B, min RTT {rtt}; {rule}{switched}; "
            f"{sends or 'nothing sent'}")


def window_note(label: str, before: Mapping[str, Any] | None,
                after: Mapping[str, Any] | None) -> str:
    """:func:`view_note` of the window between two :func:`read_stats` snapshots (either
    None: no view); ``{}`` as *before* counts from the robot's connect."""
    view = None if before is None or after is None else window_view(before, after)
    return view_note(label, view)
