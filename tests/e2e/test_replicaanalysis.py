"""The replica-failure criteria on synthetic samples, and the NATS nodes' config."""

from __future__ import annotations

import math

from fleetctl.e2e.replicaanalysis import first_after, replica_failure
from fleetctl.e2e.replicascenario import NATS_NODES, nats_config
from fleetctl.e2e.samples import Sample

S = 1_000_000_000
POSE, EVENTS = "/robot1/pose", "/robot1/events"
MARKS = {"t0": 0, "nats_kill": 10 * S, "relay_kill": 20 * S, "end": 30 * S}


def pose_stream(gaps: dict[int, int] | None = None, latency_ms: float = 2.0) -> list[Sample]:
    """A 20 Hz pose from 0 to 30 s; *gaps*: publish time (ns) -> extra delay (ns)."""
    out = []
    for i in range(600):
        pub = i * S // 20
        extra = next((d for start, d in (gaps or {}).items() if start <= pub < start + d), 0)
        out.append(Sample(POSE, i, pub, pub + int(latency_ms * 1e6) + extra, 100))
    return out


def events(seqs: list[int]) -> list[Sample]:
    return [Sample(EVENTS, s, s * S // 10, s * S // 10 + 3_000_000, 50) for s in seqs]


def result(samples: list[Sample], stayed: bool = True,
           resumed: list[Sample] | None = None) -> dict[str, dict[str, object]]:
    out = replica_failure(samples, POSE, EVENTS, {"first_seq": 0, "last_seq": 299}, MARKS,
                          stayed, events(list(range(300))) if resumed is None else resumed)
    return {c["name"]: c for c in out["criteria"]}


def test_a_clean_failover_passes_every_criterion() -> None:
    # 0.4 s without poses after the relay's kill; 0.2 s after the NATS node's.
    samples = [*pose_stream(), *events(list(range(300)))]
    samples = [s for s in samples if not (s.topic == POSE and (
        20 * S <= s.publish_time_ns < 20 * S + 4 * S // 10
        or 10 * S <= s.publish_time_ns < 10 * S + 2 * S // 10))]
    crits = result(samples)
    assert all(c["ok"] for c in crits.values()), crits
    assert crits["robot relaying through B after relay A's kill (s)"]["value"] == \
        2e-3 + 0.4


def test_a_slow_failover_a_lost_event_and_a_disconnect_fail() -> None:
    samples = [s for s in pose_stream() if not 20 * S <= s.publish_time_ns < 22 * S]
    samples += events([*range(150), *range(151, 300)])
    crits = result(samples, stayed=False)
    assert not crits["robot relaying through B after relay A's kill (s)"]["ok"]
    assert crits["no_drop events missing"]["value"] == 1
    assert not crits["viewer on B disconnected"]["ok"]


def test_duplicates_and_latency_spikes_are_caught() -> None:
    spiky = pose_stream(gaps={25 * S: S // 2})  # 0.5 s of poses held 0.5 s longer
    crits = result([*spiky, *events([*range(300), 299])])
    assert crits["no_drop events out of order or duplicated"]["value"] == 1
    ratio = crits["pose p99 over the run / quiet p99"]
    assert not ratio["ok"] and float(str(ratio["value"])) > 2.0


def test_the_resumed_sessions_gaps_reorders_and_absence_fail() -> None:
    samples = [*pose_stream(), *events(list(range(300)))]
    gap = result(samples, resumed=events([*range(200), *range(210, 300)]))
    assert gap["session resumed on B: no_drop events missing"]["value"] == 10
    swapped = events(list(range(300)))
    swapped[100], swapped[101] = swapped[101], swapped[100]
    late = [Sample(s.topic, s.seq, s.publish_time_ns, r.recv_time_ns, s.size_bytes)
            for s, r in zip(swapped, events(list(range(300))), strict=True)]
    order = result(samples, resumed=late)
    assert not order["session resumed on B: events out of order or duplicated"]["ok"]
    nothing = result(samples, resumed=[])
    assert not nothing["session resumed on B: no_drop events missing"]["ok"]


def test_nothing_after_a_mark_is_infinite() -> None:
    assert math.isinf(first_after(pose_stream()[:10], 20 * S))


def test_each_nats_node_routes_to_the_two_others() -> None:
    for name in NATS_NODES:
        text = nats_config(name)
        assert f'server_name: "{name}"' in text and "jetstream" in text
        others = [n for n in NATS_NODES if n != name]
        assert all(f"nats://{n}:6222" in text for n in others) and f"//{name}:" not in text
