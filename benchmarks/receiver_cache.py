"""What a pattern subscribe/unsubscribe costs the relay's receiver cache, in-process.

Usage::

    .venv/bin/python benchmarks/receiver_cache.py [--cached-topics 16000] [--changes 200]
        [--active-topics 50] [--subscribers 40] [--json]

A :class:`~fleetctl.server.subscriptions.SubscriptionMap` with ``--subscribers``
connections (each holding one pattern) and ``--cached-topics`` topics routed once; then one
connection toggles a pattern ``--changes`` times, and after each change a frame comes on
each of ``--active-topics`` topics (the topics in use: the cache catches up on them).
Printed: the time of one change (subscribe or unsubscribe) alone, and of one change plus
the frames after it, in microseconds (median and max over the changes). The relay runs
this on its event loop: nothing else is served meanwhile (docs/security.md, "The cost of
a regex against many topics or many patterns"). Run it against another checkout with
``PYTHONPATH=/path/to/checkout``.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import statistics
import sys
import time
from pathlib import Path

from fleetctl.server.authmap import parse_auth_map
from fleetctl.server.permissions import PermissionsPool
from fleetctl.server.subscriptions import SubscriptionMap


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cached-topics", type=int, default=16000)
    parser.add_argument("--changes", type=int, default=200)
    parser.add_argument("--active-topics", type=int, default=50)
    parser.add_argument("--subscribers", type=int, default=40)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    auth = parse_auth_map({"version": 1, "identities": [
        {"name": "viewer", "ip": "10.0.0.1", "rules": [{"topic": ".*", "op": "receive"}]}]},
        Path("bench-auth.yaml"))
    perms = PermissionsPool().get(auth.match_address(ipaddress.ip_address("10.0.0.1")))
    subs: SubscriptionMap[str] = SubscriptionMap(256)
    for i in range(args.subscribers):
        subs.subscribe(f"viewer{i}", perms, f"/r{i}/.*")
    topics = [f"/r{i // 40}/t{i}" for i in range(args.cached_topics)]
    for topic in topics:
        subs.receivers(topic)
    active = topics[:: max(1, len(topics) // max(1, args.active_topics))][:args.active_topics]
    alone: list[float] = []
    with_frames: list[float] = []
    for n in range(args.changes):
        started = time.perf_counter()
        if n % 2 == 0:
            subs.subscribe("churner", perms, "/t0/x.*")
        else:
            subs.unsubscribe("churner", "/t0/x.*")
        changed = time.perf_counter()
        for topic in active:
            subs.receivers(topic)
        done = time.perf_counter()
        alone.append((changed - started) * 1e6)
        with_frames.append((done - started) * 1e6)
    result = {"cached_topics": args.cached_topics, "active_topics": len(active),
              "subscribers": args.subscribers, "changes": args.changes,
              "change_us_median": statistics.median(alone), "change_us_max": max(alone),
              "with_frames_us_median": statistics.median(with_frames),
              "with_frames_us_max": max(with_frames)}
    if args.json:
        json.dump(result, sys.stdout, indent=2)
        print()
        return
    print(f"{args.cached_topics} topics cached, {args.subscribers} subscribers, "
          f"{args.changes} pattern changes, a frame on {len(active)} topics after each")
    print(f"one change: median {result['change_us_median']:.1f} us, "
          f"max {result['change_us_max']:.1f} us")
    print(f"one change and its frames: median {result['with_frames_us_median']:.1f} us, "
          f"max {result['with_frames_us_max']:.1f} us")


if __name__ == "__main__":
    main()
