"""What a new subscription costs the relay's event loop beside full latched and video
stores, in-process: the matching and queueing of its first frames.

Usage::

    .venv/bin/python benchmarks/first_frames.py [--latched-topics 4096]
        [--video-topics 4096] [--held 0] [--repeats 51] [--json]

A :class:`~fleetctl.server.relay.RelayCore` holds ``--latched-topics`` latched messages
(``/r<i // 32>/map<i>``: 32 topics per robot) and knows a publisher for each of
``--video-topics`` video topics (``/r<i // 32>/cam<i>``); one viewer that may receive
everything holds ``--held`` other patterns (``/held<k>/.*``). Then, ``--repeats`` times
each, the viewer subscribes to a pattern and unsubscribes: the time of the subscribe
(``RelayCore._subscribe``: checks, the first frames looked up and queued, the latched
messages and keyframe requests included) is printed, median and max, in milliseconds, for

- ``prefix``: ``/r7/.*`` (64 topics: 32 latched, 32 video),
- ``literal``: ``/r7/map230``,
- ``suffix``: ``.*scan`` (no topic matches; RE2 cannot bound it),
- ``all``: ``.*`` (every topic: 4,096 latched messages and 4,096 keyframe requests queued),

and, where the code has it, the control requests the subscribe was charged
(docs/security.md, "The cost of a regex against many topics or many patterns"). The clock
the core is given advances 100 s before each subscribe, so each one asks for its
keyframes again and finds its control requests refilled; one subscribe of each pattern
before the timed ones warms the caches.
Run it against another checkout with ``PYTHONPATH=/path/to/checkout``.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from fleetctl.server.authmap import parse_auth_map
from fleetctl.server.config import ServerConfig
from fleetctl.server.metrics import Metrics
from fleetctl.server.registry import RobotRegistry
from fleetctl.server.relay import Peer, RelayCore

PATTERNS = {"prefix": "/r7/.*", "literal": "/r7/map230", "suffix": ".*scan", "all": ".*"}


class _Clock:
    """The core's clock: advanced by hand (keyframe requests' per-topic interval)."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def _core(clock: _Clock) -> RelayCore:
    auth = parse_auth_map({"version": 1, "identities": [
        {"name": "viewer", "ip": "10.0.0.1", "rules": [{"topic": ".*", "op": "both"}]},
        {"name": "robot", "ip": "10.0.0.2", "rules": [{"topic": ".*", "op": "send"}]}]},
        Path("bench-auth.yaml"))
    return RelayCore(ServerConfig(), auth, RobotRegistry(None, 5.0), Metrics(), clock)


def _peer(core: RelayCore, address: str) -> Peer:
    peer = core.new_peer(address, lambda code, reason: None, None)
    core.authenticate(peer, core.auth.match_address(ipaddress.ip_address(address)))
    return peer


def _level(core: RelayCore, peer: Peer) -> float | None:
    """Control requests left to *peer* (None: a checkout without per-subscribe charges)."""
    bucket = getattr(core, "_control_bucket", None)
    return bucket(peer).level() if bucket is not None else None


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Fill the stores, then time each pattern's subscribes."""
    clock = _Clock()
    core = _core(clock)
    robot, viewer = _peer(core, "10.0.0.2"), _peer(core, "10.0.0.1")
    for i in range(args.latched_topics):
        core.latched.put(("robot",), f"/r{i // 32}/map{i}", b"m" * 64, None)
    for i in range(args.video_topics):
        core.keyframes.note_publisher(f"/r{i // 32}/cam{i}", robot)
    for k in range(args.held):
        core.subs.subscribe(viewer, viewer.perms, f"/held{k}/.*", viewer.identity_names)
    results: dict[str, Any] = {}
    for name, pattern in PATTERNS.items():
        took: list[float] = []
        charged: list[float] = []
        for _ in range(args.repeats + 1):
            clock.now_s += 100.0
            viewer.outbound.pop_batch(10**9)
            robot.outbound.pop_batch(10**9)
            before = _level(core, viewer)
            started = time.perf_counter()
            core._subscribe(viewer, pattern)
            took.append((time.perf_counter() - started) * 1000)
            after = _level(core, viewer)
            if before is not None and after is not None:
                charged.append(before - after)
            core.subs.unsubscribe(viewer, pattern)
        took, charged = took[1:], charged[1:]  # the first one warmed the caches
        results[name] = {"pattern": pattern, "ms_median": statistics.median(took),
                         "ms_max": max(took),
                         "charged": statistics.median(charged) if charged else None}
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--latched-topics", type=int, default=4096)
    parser.add_argument("--video-topics", type=int, default=4096)
    parser.add_argument("--held", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=51)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    results = measure(args)
    if args.json:
        json.dump(results, sys.stdout, indent=2)
        print()
        return
    print(f"{args.latched_topics} latched topics, {args.video_topics} video topics, "
          f"{args.held} other patterns held, {args.repeats} subscribes each")
    for name, r in results.items():
        charged = "-" if r["charged"] is None else f"{r['charged']:.0f}"
        print(f"{name:>8} {r['pattern']:<12} median {r['ms_median']:8.3f} ms  "
              f"max {r['ms_max']:8.3f} ms  control requests charged {charged}")


if __name__ == "__main__":
    main()
