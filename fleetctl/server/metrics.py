"""Prometheus metrics of the relay, rendered by hand in the text exposition format 0.0.4.

Counters live in plain dicts keyed by topic: the relay increments them on every frame, so
they must cost one dict update. Topic labels are bounded (:data:`MAX_TOPIC_LABELS`);
topics past the bound are counted under ``topic="<other>"`` until
:meth:`Metrics.forget_idle` makes room by forgetting topics idle for an hour.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TypeVar

# Why: topic names come from clients; an unbounded label set is a memory and scrape hazard.
MAX_TOPIC_LABELS = 2000
OTHER = "<other>"
K = TypeVar("K", str, tuple[str, str])  # a label: a topic, or a session and topic
# A full label table forgets the topics (and session/topic pairs) whose counters have not
# moved for this long, seconds. Why: the first 2,000 topics kept their labels for good, so
# on a relay whose robots come and go under new names (sims, replays, renames: the relay
# soak used up the table in 12 minutes) /metrics went on showing gone robots' topics and
# counted every new one under <other>. A forgotten series ends; should the topic come
# back, its counter starts again from 0, which Prometheus reads as a counter reset.
IDLE_LABEL_S = 3600.0
# How often forget_idle looks at the counters, seconds: a copy of the tables' values,
# about a millisecond when full, so the per-frame counting stays one dict update.
IDLE_SWEEP_PERIOD_S = 60.0


@dataclass
class Metrics:
    """All counters and gauges of one server."""

    connections_total: int = 0
    connections_open: int = 0
    messages_in: dict[str, int] = field(default_factory=dict)
    bytes_in: dict[str, int] = field(default_factory=dict)
    messages_out: dict[str, int] = field(default_factory=dict)
    bytes_out: dict[str, int] = field(default_factory=dict)
    drops: dict[str, int] = field(default_factory=dict)
    errors: dict[str, int] = field(default_factory=dict)
    closes: dict[int, int] = field(default_factory=dict)
    session_drops: dict[tuple[str, str], int] = field(default_factory=dict)
    auth_reloads: int = 0
    auth_reload_failures: int = 0
    connections_refused: dict[str, int] = field(default_factory=dict)
    # Pongs replaced by a newer one: pings read together, or while the peer did not read
    # (RelayConnection).
    pongs_coalesced: int = 0
    # Connections not read for a moment (a rate of their identity set), by reason.
    reads_paused: dict[str, int] = field(default_factory=dict)
    # The latched store (fleetctl.server.latched): events by name, and two gauges it sets.
    latched_events: dict[str, int] = field(default_factory=dict)
    latched_bytes: int = 0
    latched_messages: int = 0
    latched_delivered: int = 0  # frames queued to new subscribers
    # Keyframe requests (fleetctl.server.keyframes) by outcome.
    keyframe_requests: dict[str, int] = field(default_factory=dict)
    # Labels forgotten by forget_idle (topics and session/topic pairs).
    labels_forgotten: int = 0
    # forget_idle's memory: per label, its counters when they last moved and since when.
    _topics_moved: dict[str, tuple[tuple[int, ...], float]] = field(default_factory=dict,
                                                                    repr=False)
    _pairs_moved: dict[tuple[str, str], tuple[tuple[int, ...], float]] = field(
        default_factory=dict, repr=False)
    _swept_at_s: float = field(default=float("-inf"), repr=False)

    def label(self, topic: str) -> str:
        """Return *topic*, or ``<other>`` once the label bound is reached."""
        if topic in self.messages_in or len(self.messages_in) < MAX_TOPIC_LABELS:
            return topic
        return OTHER

    def count_in(self, topic: str, nbytes: int) -> None:
        """Count one frame received on *topic*."""
        if topic not in self.messages_in:
            topic = self.label(topic)
        self.messages_in[topic] = self.messages_in.get(topic, 0) + 1
        self.bytes_in[topic] = self.bytes_in.get(topic, 0) + nbytes

    def count_out(self, topic: str, nbytes: int) -> None:
        """Count one frame written to a connection."""
        if topic not in self.messages_out:
            topic = self.label(topic)
        self.messages_out[topic] = self.messages_out.get(topic, 0) + 1
        self.bytes_out[topic] = self.bytes_out.get(topic, 0) + nbytes

    def count_drop(self, topic: str, n: int = 1) -> None:
        """Count *n* frames dropped by an outbound scheduler."""
        if topic not in self.drops:
            topic = self.label(topic)
        self.drops[topic] = self.drops.get(topic, 0) + n

    def count_session_drop(self, session: str, topic: str) -> None:
        """Count one no_drop frame dropped from (or expired with) *session*'s mailbox."""
        key = (session, topic)
        if key not in self.session_drops and len(self.session_drops) >= MAX_TOPIC_LABELS:
            key = (OTHER, OTHER)
        self.session_drops[key] = self.session_drops.get(key, 0) + 1

    def count_keyframe_request(self, outcome: str) -> None:
        """Count one keyframe request by *outcome* (``forwarded``, ``rate_limited``...)."""
        self.keyframe_requests[outcome] = self.keyframe_requests.get(outcome, 0) + 1

    def count_read_paused(self, reason: str) -> None:
        """Count one pause of a connection's reading (``control_rate``,
        ``new_topic_rate``)."""
        self.reads_paused[reason] = self.reads_paused.get(reason, 0) + 1

    def count_error(self, code: str) -> None:
        """Count one error frame (or would-be error frame) of *code*."""
        self.errors[code] = self.errors.get(code, 0) + 1

    def count_close(self, code: int) -> None:
        """Count one connection the server closed with *code*."""
        self.closes[code] = self.closes.get(code, 0) + 1

    def forget_idle(self, now_s: float) -> int:
        """Every :data:`IDLE_SWEEP_PERIOD_S`: note which labels' counters moved, and in a
        full label table (the topics', the session/topic pairs'), forget the labels idle
        for :data:`IDLE_LABEL_S` (never ``<other>``); return how many were forgotten.
        *now_s*: a monotonic clock, seconds."""
        if now_s - self._swept_at_s < IDLE_SWEEP_PERIOD_S:
            return 0
        self._swept_at_s = now_s
        topic_tables = (self.messages_in, self.bytes_in, self.messages_out, self.bytes_out,
                        self.drops)
        topics = {t: (self.messages_in.get(t, 0), self.messages_out.get(t, 0),
                      self.drops.get(t, 0))
                  for t in self.messages_in.keys() | self.messages_out.keys()
                  | self.drops.keys()}
        idle_topics = _idle(self._topics_moved, topics, now_s, OTHER,
                            full=len(self.messages_in) >= MAX_TOPIC_LABELS)
        for topic in idle_topics:
            for table in topic_tables:
                table.pop(topic, None)
        pairs = {k: (n,) for k, n in self.session_drops.items()}
        idle_pairs = _idle(self._pairs_moved, pairs, now_s, (OTHER, OTHER),
                           full=len(self.session_drops) >= MAX_TOPIC_LABELS)
        for pair in idle_pairs:
            del self.session_drops[pair]
        forgotten = len(idle_topics) + len(idle_pairs)
        self.labels_forgotten += forgotten
        return forgotten

    def render(
        self,
        gauges: Iterable[tuple[str, str, dict[str, float]]] = (),
        labelled: Iterable[tuple[str, str, str, dict[str, float]]] = (),
        families: Iterable[tuple[str, str, str, str, dict[str, float]]] = (),
    ) -> str:
        """Return the exposition text.

        Args:
            gauges: Extra ``(name, help, {label_value: value})`` gauges keyed by connection
                (queue depths), computed by the caller at scrape time.
            labelled: Extra ``(name, help, label_name, {label_value: value})`` gauges
                (sessions), computed by the caller at scrape time.
            families: Extra ``(name, type, help, label_name, {label_value: value})``
                counters or gauges (the recorder's); label_name ``""`` renders the one
                value unlabelled.
        """
        out: list[str] = []
        _scalar(out, "fleetctl_connections_total", "counter", "Connections accepted.",
                self.connections_total)
        _scalar(out, "fleetctl_connections_open", "gauge", "Connections open now.",
                self.connections_open)
        _scalar(out, "fleetctl_auth_reloads_total", "counter",
                "Auth map reloads applied (file change or SIGHUP).", self.auth_reloads)
        _scalar(out, "fleetctl_auth_reload_failures_total", "counter",
                "Auth map reloads refused (unreadable or invalid file; the previous map "
                "stays).", self.auth_reload_failures)
        by_topic = (
            ("fleetctl_messages_in_total", "Frames received per topic.", self.messages_in),
            ("fleetctl_bytes_in_total", "Bytes received per topic.", self.bytes_in),
            ("fleetctl_messages_out_total", "Frames written per topic.", self.messages_out),
            ("fleetctl_bytes_out_total", "Bytes written per topic.", self.bytes_out),
            ("fleetctl_drops_total", "Frames dropped by outbound schedulers per topic.",
             self.drops),
        )
        for name, help_text, values in by_topic:
            _labelled(out, name, "counter", help_text, "topic", values)
        _labelled(out, "fleetctl_errors_total", "counter", "Error frames per code.", "code",
                  self.errors)
        _labelled(out, "fleetctl_connections_refused_total", "counter",
                  "Connections aborted at accept: unauthenticated connections at their "
                  "cap (total, per_address).", "cap", self.connections_refused)
        _scalar(out, "fleetctl_metric_labels_forgotten_total", "counter",
                "Topic (and session/topic) labels forgotten after an hour without a "
                "count while their table was full: their series end here.",
                self.labels_forgotten)
        _labelled(out, "fleetctl_reads_paused_total", "counter",
                  "Times a connection was not read for a moment because its identity set "
                  "went over a rate (control_rate: control requests; new_topic_rate: "
                  "frames on new topics). What it had sent waits and is taken once the "
                  "rate allows, in order: nothing is dropped (a Foxglove connection's "
                  "frames meanwhile are: fleetctl_errors_total{code=\"rate_limited\"}).",
                  "reason", self.reads_paused)
        _scalar(out, "fleetctl_pongs_coalesced_total", "counter",
                "Pongs not sent because the answer to a later ping replaced them "
                "(RFC 6455 5.5.3): pings read together, or the peer did not read.",
                self.pongs_coalesced)
        self._render_latched(out)
        closes = {str(k): v for k, v in self.closes.items()}
        _labelled(out, "fleetctl_closes_total", "counter",
                  "Connections closed by the server per close code.", "code", closes)
        name = "fleetctl_session_mailbox_drops_total"
        out += [f"# HELP {name} no_drop frames dropped from offline sessions' mailboxes "
                "(overflow, expiry) per session and topic.", f"# TYPE {name} counter"]
        out += [f'{name}{{session="{_escape(s)}",topic="{_escape(t)}"}} {v}'
                for (s, t), v in sorted(self.session_drops.items())]
        for gauge, help_text, per_conn in gauges:
            _labelled(out, gauge, "gauge", help_text, "connection", per_conn)
        for gauge, help_text, label_name, label_values in labelled:
            _labelled(out, gauge, "gauge", help_text, label_name, label_values)
        for name, kind, help_text, label_name, label_values in families:
            if label_name:
                _labelled(out, name, kind, help_text, label_name, label_values)
            else:
                _scalar(out, name, kind, help_text, sum(label_values.values()))
        return "\n".join(out) + "\n"

    def _render_latched(self, out: list[str]) -> None:
        _scalar(out, "fleetctl_latched_bytes", "gauge",
                "Bytes of latched messages kept (complete and still arriving).",
                self.latched_bytes)
        _scalar(out, "fleetctl_latched_messages", "gauge",
                "Complete latched messages kept (one per sender and topic).",
                self.latched_messages)
        _labelled(out, "fleetctl_latched_events_total", "counter",
                  "Latched store events: stored, evicted (byte or entry bound), "
                  "refused_too_big, superseded (incomplete message replaced), malformed, "
                  "revoked (sender's permission gone).", "event", self.latched_events)
        _scalar(out, "fleetctl_latched_delivered_frames_total", "counter",
                "Stored latched frames queued to new subscribers.", self.latched_delivered)
        _labelled(out, "fleetctl_keyframe_requests_total", "counter",
                  "Keyframe requests by outcome: forwarded, auto (sent by the server for "
                  "a new subscriber), rate_limited, refused (may not receive the topic), "
                  "no_publisher, malformed.", "outcome", self.keyframe_requests)


def _idle(moved: dict[K, tuple[tuple[int, ...], float]], counts: Mapping[K, tuple[int, ...]],
             now_s: float, keep: K, *, full: bool) -> list[K]:
    """Note in *moved* which labels' *counts* changed since the last sweep (forgetting
    labels no longer counted); when the table is *full*, take out and return those idle
    for :data:`IDLE_LABEL_S`, never *keep* (``<other>``)."""
    for key in moved.keys() - counts.keys():
        del moved[key]
    for key, now in counts.items():
        if key not in moved or moved[key][0] != now:
            moved[key] = (now, now_s)
    if not full:
        return []
    idle = [k for k, (_, since) in moved.items() if now_s - since >= IDLE_LABEL_S and k != keep]
    for key in idle:
        del moved[key]
    return idle


def _scalar(out: list[str], name: str, kind: str, help_text: str, value: float) -> None:
    out += [f"# HELP {name} {help_text}", f"# TYPE {name} {kind}", f"{name} {value}"]


def _labelled(
    out: list[str], name: str, kind: str, help_text: str, label: str,
    values: dict[str, int] | dict[str, float],
) -> None:
    out += [f"# HELP {name} {help_text}", f"# TYPE {name} {kind}"]
    out += [f'{name}{{{label}="{_escape(k)}"}} {v}' for k, v in sorted(values.items())]


def _escape(value: str) -> str:
    # Exposition format: backslash, double quote and newline are escaped in label values.
    return value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")

