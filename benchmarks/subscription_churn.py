"""An honest subscriber's frames and latency while one token churns subscriptions.

Usage::

    .venv/bin/python benchmarks/subscription_churn.py [--seconds 3] [--rounds 3]
        [--rate-hz 1000] [--churners 8] [--server-cpu 0] [--client-cpu 1] [--churn-cpu 2]
        [--cached-topics 16000] [--latched-topics 4096] [--churn-kind pattern]
        [--held 0] [--json]

Project issue 14, item 2. Three processes: the relay (:class:`RelayServer`, defaults,
pinned to one core), the churning token (its own process and core) and the honest side
(publisher and subscriber, another core; the churning process is niced and shares the
client core unless ``--churn-cpu`` says otherwise). Each round measures two phases side by side:

- ``quiet``: the publisher sends small no_drop frames at ``--rate-hz`` on one topic
  (no_drop: a missing frame is one the relay could not deliver, not one superseded by
  design); the honest subscriber (its own token) counts what it gets and the latency of
  each frame (publish stamp to receipt, one host clock); a fresh client connects,
  subscribes and gets its ``subscribed`` (``join_ms``);
- ``churn``: the same while ``--churners`` connections of one attacker token, each
  holding a named session and as many 4 KiB patterns as the server takes, send
  subscribe/unsubscribe pairs as fast as TCP lets them, reconnecting whenever the server
  closes them (4429), so the token churns as fast as the server lets it.

``--cached-topics N`` first has publishers send one frame on each of N distinct topics
(``/fill/r<i // 40>/t<i>``: 40 topics per robot), so the relay's receiver cache holds N
topics while the rounds run (docs/security.md, "The cost of a regex against many topics";
several publisher identities, as the new-topic rate allows each 4096 at once).
``--latched-topics N`` first has senders store a latched message on each of N topics
(``/latched/r<i // 32>/t<i>``; the store keeps 4,096), so every new subscription is
matched against a full latched store (docs/security.md, "A subscribe or unsubscribe").
``--churn-kind`` says what the churners toggle: ``literal`` a topic, ``pattern`` a regex
with a literal prefix (``/t<i>/x.*``), ``wide`` one RE2 cannot bound (``.*/x<i>``: every
stored topic looked at, none matched), ``all`` ``.*`` (every stored latched message
delivered to the churner again). ``--held N`` is how many 4 KiB patterns each churner
tries to hold (255: as many as the server takes).

Printed per phase: frames received / sent, latency p50 and p99, the join time, and what
the server answered the churners (changes applied vs refused). The bar: in ``churn`` the
subscriber keeps >= 99 % of its frames and its p99 stays within 2x of ``quiet``.
Medians over the rounds.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

TOPIC = "/bench/telemetry"
PUBLISHER, HONEST, ATTACKER = "publisher-token", "honest-token", "attacker-token"
FILLERS = 5  # identities that fill the cache: 4000 new topics each (the burst is 4096)
FILL_PER_IDENTITY = 4000
LATCHERS = 2  # identities that fill the latched store (4,096 topics at most)
MAX_LATCHED = LATCHERS * FILL_PER_IDENTITY
# What each churner toggles, by --churn-kind (i: the churner's index).
TOGGLED = {"literal": "/t{i}/x", "pattern": "/t{i}/x.*", "wide": ".*/x{i}", "all": ".*"}
FILL_DONE = "/fill/done"
MAX_CACHED = FILLERS * FILL_PER_IDENTITY


def _pin(cpu: int) -> None:
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setaffinity(0, {cpu})


def _auth_yaml(path: Path) -> None:
    from fleetctl.tokens import hash_token

    lines = ["version: 1", "identities:"]
    fillers = [(f"filler{k}", f"filler-token-{k}", "send") for k in range(FILLERS)]
    fillers += [(f"latcher{k}", f"latcher-token-{k}", "send") for k in range(LATCHERS)]
    for name, token, op in (("publisher", PUBLISHER, "send"), ("honest", HONEST, "receive"),
                            ("attacker", ATTACKER, "receive"), *fillers):
        lines += [f"  - name: {name}", f"    token_sha256: {hash_token(token)}",
                  "    rules:", f"      - {{topic: '.*', op: {op}}}"]
    path.write_text("\n".join(lines) + "\n")


def run_server(cpu: int, directory: str, ports: Any) -> None:
    """The relay with default limits, until terminated."""
    _pin(cpu)
    from fleetctl.server.app import RelayServer
    from fleetctl.server.config import ServerConfig

    base = Path(directory)
    _auth_yaml(base / "auth.yaml")
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0,
                          auth_map=base / "auth.yaml", database=base / "fleet.db")

    async def main() -> None:
        async with RelayServer(config) as server:
            ports.put(server.port)
            await asyncio.Event().wait()

    asyncio.run(main())


# -- the churning token -----------------------------------------------------------------


def run_churn(cpu: int, port: int, churners: int, stop: Any, results: Any,
              kind: str = "literal", held_count: int = 255) -> None:
    """*churners* connections of the attacker token toggling subscriptions flat out.

    Niced: on a small machine it shares a core with the honest clients, and the figure
    wanted is what the *server* does, not how the OS shares a client core."""
    _pin(cpu)
    with contextlib.suppress(OSError):
        os.nice(10)
    counts = {"subscribed": 0, "unsubscribed": 0, "refused": 0, "connects": 0}

    async def one(index: int) -> None:
        from websockets.asyncio.client import connect

        from fleetctl.wire.control import encode_subscription

        held = [encode_subscription(f"/held{index}_{i}/(" + "a|" * 2040 + "b)")
                for i in range(held_count)]
        toggled = TOGGLED[kind].format(i=index)
        toggle = [encode_subscription(toggled, s) for s in (True, False)]
        while not stop.is_set():
            counts["connects"] += 1
            with contextlib.suppress(Exception):
                async with connect(f"ws://127.0.0.1:{port}/", max_size=None, close_timeout=0.1,
                                   additional_headers={
                                       "Authorization": f"Bearer {ATTACKER}",
                                       "X-Fleetctl-Session": f"churn{index}"}) as ws:
                    reader = asyncio.create_task(_count(ws, counts))
                    for frame in held:
                        await ws.send(frame)
                    while not stop.is_set() and not reader.done():
                        await ws.send(toggle[0])
                        await ws.send(toggle[1])
                        # send() yields only once TCP pushes back: without this the
                        # reader never ran (answers uncounted) until the buffers filled
                        await asyncio.sleep(0)
                    reader.cancel()

    async def main() -> None:
        tasks = [asyncio.create_task(one(i)) for i in range(churners)]
        while not stop.is_set():  # polling a cross-process event: not synchronization
            await asyncio.sleep(0.1)
        for task in tasks:  # a throttled send may be blocked: cancel, do not wait
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    asyncio.run(main())
    results.put(counts)


async def _count(ws: Any, counts: dict[str, int]) -> None:
    with contextlib.suppress(Exception):
        async for message in ws:
            if isinstance(message, str):
                kind = json.loads(message).get("type")
                if kind in ("subscribed", "unsubscribed"):
                    counts[kind] += 1
                elif kind == "error":
                    counts["refused"] += 1


# -- filling the receiver cache ----------------------------------------------------------


async def fill_cache(port: int, count: int) -> float:
    """One frame on each of *count* new topics, then a marker the honest token waits for
    (frames of one connection are handled in order); returns the seconds it took."""
    from websockets.asyncio.client import connect

    from fleetctl.wire.codec import default_codec
    from fleetctl.wire.control import encode_subscription

    codec = default_codec()
    cls = codec.registry.get("std_msgs/msg/String").cls
    url = f"ws://127.0.0.1:{port}/"
    started = time.perf_counter()
    async with connect(url, additional_headers={"Authorization": f"Bearer {HONEST}"}) as sub:
        await sub.send(encode_subscription(FILL_DONE))
        while not (isinstance(m := await sub.recv(), str) and "subscribed" in m):
            pass
        for k, first in enumerate(range(0, count, FILL_PER_IDENTITY)):
            async with connect(url, additional_headers={
                    "Authorization": f"Bearer filler-token-{k}"}) as pub:
                for i in range(first, min(count, first + FILL_PER_IDENTITY)):
                    await pub.send(codec.encode(cls("x"), "std_msgs/msg/String",
                                                f"/fill/r{i // 40}/t{i}"))
                await pub.send(codec.encode(cls("done"), "std_msgs/msg/String", FILL_DONE,
                                            no_drop=True))
                while not isinstance(await sub.recv(), bytes):
                    pass
    return time.perf_counter() - started


async def fill_latched(port: int, count: int) -> float:
    """A latched message on each of *count* topics, by as many identities as the
    new-topic rate asks; returns the seconds it took until the relay had them all (the
    honest token asks for them: it gets them once all are stored, in order)."""
    from websockets.asyncio.client import connect

    from fleetctl.wire.codec import default_codec
    from fleetctl.wire.control import encode_subscription

    codec = default_codec()
    cls = codec.registry.get("std_msgs/msg/String").cls
    url = f"ws://127.0.0.1:{port}/"
    started = time.perf_counter()
    for k, first in enumerate(range(0, count, FILL_PER_IDENTITY)):
        async with connect(url, additional_headers={
                "Authorization": f"Bearer latcher-token-{k}"}) as pub:
            for i in range(first, min(count, first + FILL_PER_IDENTITY)):
                await pub.send(codec.encode(cls("x" * 64), "std_msgs/msg/String",
                                            f"/latched/r{i // 32}/t{i}", latched=True))
    kept = min(count, 4096)  # the store's bound (LatchedStore.max_entries)
    async with connect(url, additional_headers={"Authorization": f"Bearer {HONEST}"}) as sub:
        while True:  # until a new subscriber gets every one (they all arrived)
            await sub.send(encode_subscription("/latched/.*"))
            got = 0
            with contextlib.suppress(TimeoutError):
                while got < kept:
                    if isinstance(await asyncio.wait_for(sub.recv(), 2.0), bytes):
                        got += 1
            if got >= kept:
                return time.perf_counter() - started
            await sub.send(encode_subscription("/latched/.*", False))


# -- the honest side ----------------------------------------------------------------------


async def _join_ms(port: int) -> float:
    """Connect, authenticate, subscribe, get ``subscribed``: the time it takes."""
    from websockets.asyncio.client import connect

    from fleetctl.wire.control import encode_subscription

    started = time.perf_counter()
    async with connect(f"ws://127.0.0.1:{port}/",
                       additional_headers={"Authorization": f"Bearer {HONEST}"}) as ws:
        await ws.send(encode_subscription("/join/x"))
        while True:
            message = await ws.recv()
            if isinstance(message, str) and json.loads(message)["type"] == "subscribed":
                return (time.perf_counter() - started) * 1000


async def measure(port: int, seconds: float, rate_hz: float) -> dict[str, float]:
    """Publish at *rate_hz* for *seconds*; what the honest subscriber got."""
    from websockets.asyncio.client import connect

    from fleetctl.wire.codec import default_codec
    from fleetctl.wire.control import encode_subscription
    from fleetctl.wire.metadata import read_metadata

    codec = default_codec()
    cls = codec.registry.get("std_msgs/msg/String").cls
    latencies: list[float] = []
    url = f"ws://127.0.0.1:{port}/"
    async with connect(url, additional_headers={"Authorization": f"Bearer {HONEST}"}) as sub, \
            connect(url, additional_headers={"Authorization": f"Bearer {PUBLISHER}"}) as pub:
        await sub.send(encode_subscription(TOPIC))
        while not (isinstance(m := await sub.recv(), str) and "subscribed" in m):
            pass

        async def receive() -> None:
            async for message in sub:
                if isinstance(message, bytes):
                    sent = read_metadata(message).publish_time_ns
                    latencies.append((time.time_ns() - sent) / 1e6)

        reader = asyncio.create_task(receive())
        sent = 0
        start = time.perf_counter()
        join = 0.0
        while (elapsed := time.perf_counter() - start) < seconds:
            if sent < elapsed * rate_hz:
                await pub.send(codec.encode(cls("x" * 64), "std_msgs/msg/String", TOPIC,
                                            no_drop=True, publish_time_ns=time.time_ns(),
                                            seq=sent + 1))
                sent += 1
            else:
                await asyncio.sleep(1 / rate_hz / 4)  # pacing the publisher
            if not join and elapsed > seconds / 2:
                join = await _join_ms(port)
        await asyncio.sleep(0.2)  # the last frames in flight (measurement tail, not sync)
        reader.cancel()
    ordered = sorted(latencies) or [float("nan")]
    return {"sent": sent, "received": len(latencies), "fraction": len(latencies) / sent,
            "p50_ms": ordered[len(ordered) // 2],
            "p99_ms": ordered[min(len(ordered) - 1, int(len(ordered) * 0.99))],
            "join_ms": join}


def one_round(port: int, args: argparse.Namespace) -> dict[str, Any]:
    """A quiet phase, then a churn phase."""
    _pin(args.client_cpu)
    quiet = asyncio.run(measure(port, args.seconds, args.rate_hz))
    stop, results = mp.Event(), mp.Queue()
    churn = mp.Process(target=run_churn, args=(args.churn_cpu, port, args.churners, stop,
                                               results, args.churn_kind, args.held))
    churn.start()
    try:
        time.sleep(1.0)  # let the churners connect and load their patterns (warm-up)
        try:
            loud = asyncio.run(measure(port, args.seconds, args.rate_hz))
        except TimeoutError:  # the relay did not even complete a handshake in 10 s
            nan = float("nan")
            loud = {"sent": 0, "received": 0, "fraction": 0.0, "p50_ms": nan,
                    "p99_ms": nan, "join_ms": nan, "stalled": True}
    finally:
        stop.set()
        counts = results.get(timeout=60)
        churn.join(timeout=10)
    return {"quiet": quiet, "churn": loud, "churner": counts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--rate-hz", type=float, default=1000.0)
    parser.add_argument("--churners", type=int, default=8)
    parser.add_argument("--server-cpu", type=int, default=0)
    parser.add_argument("--client-cpu", type=int, default=1)
    parser.add_argument("--churn-cpu", type=int, default=-1,
                        help="core of the churning process (default: the client core)")
    parser.add_argument("--cached-topics", type=int, default=0,
                        help=f"topics in the receiver cache during the rounds (at most "
                             f"{MAX_CACHED})")
    parser.add_argument("--latched-topics", type=int, default=0,
                        help=f"latched messages stored before the rounds (at most "
                             f"{MAX_LATCHED}; the store keeps 4096)")
    parser.add_argument("--churn-kind", choices=tuple(TOGGLED), default="literal",
                        help="what the churners toggle: " + ", ".join(
                            f"{k} ({v})" for k, v in TOGGLED.items()))
    parser.add_argument("--held", type=int, default=255,
                        help="4 KiB patterns each churner tries to hold (0-255)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if not 0 <= args.cached_topics <= MAX_CACHED:
        parser.error(f"--cached-topics: 0 to {MAX_CACHED}")
    if not 0 <= args.latched_topics <= MAX_LATCHED:
        parser.error(f"--latched-topics: 0 to {MAX_LATCHED}")
    if not 0 <= args.held <= 255:
        parser.error("--held: 0 to 255")
    if args.churn_cpu < 0:
        args.churn_cpu = args.client_cpu
    with tempfile.TemporaryDirectory() as directory:
        ports: Any = mp.Queue()
        server = mp.Process(target=run_server, args=(args.server_cpu, directory, ports),
                            daemon=True)
        server.start()
        try:
            port = ports.get(timeout=30)
            if args.cached_topics:
                _pin(args.client_cpu)
                took = asyncio.run(fill_cache(port, args.cached_topics))
                print(f"{args.cached_topics} topics cached in {took:.1f} s", file=sys.stderr)
            if args.latched_topics:
                _pin(args.client_cpu)
                took = asyncio.run(fill_latched(port, args.latched_topics))
                print(f"{args.latched_topics} latched messages stored in {took:.1f} s",
                      file=sys.stderr)
            rounds = [one_round(port, args) for _ in range(args.rounds)]
        finally:
            server.terminate()
            server.join()
    report(rounds, args)


def report(rounds: list[dict[str, Any]], args: argparse.Namespace) -> None:
    """Print each round and the medians (or JSON)."""
    def med(phase: str, key: str) -> float:
        return statistics.median(r[phase][key] for r in rounds)

    summary = {phase: {k: med(phase, k) for k in ("fraction", "p50_ms", "p99_ms", "join_ms")}
               for phase in ("quiet", "churn")}
    if args.json:
        json.dump({"rounds": rounds, "median": summary}, sys.stdout, indent=2)
        print()
        return
    print(f"{args.rate_hz:g} Hz for {args.seconds:g} s per phase, {args.churners} churning "
          f"connections of one token toggling a {args.churn_kind} (holding up to "
          f"{args.held} patterns), {args.cached_topics} topics cached, "
          f"{args.latched_topics} latched messages stored, {args.rounds} rounds")
    print(f"{'round':>5} {'phase':>6} {'frames':>14} {'p50 ms':>8} {'p99 ms':>8} "
          f"{'join ms':>8}  churner")
    for i, r in enumerate(rounds, 1):
        for phase in ("quiet", "churn"):
            m = r[phase]
            extra = json.dumps(r["churner"]) if phase == "churn" else ""
            if m.get("stalled"):
                extra = "STALLED: the honest client's handshake timed out (10 s) " + extra
            print(f"{i:>5} {phase:>6} {m['received']:>6}/{m['sent']:<6} {m['p50_ms']:>8.2f} "
                  f"{m['p99_ms']:>8.2f} {m['join_ms']:>8.1f}  {extra}")
    q, c = summary["quiet"], summary["churn"]
    print(f"median quiet: {q['fraction']:.1%} of frames, p50 {q['p50_ms']:.2f} ms, "
          f"p99 {q['p99_ms']:.2f} ms, join {q['join_ms']:.1f} ms")
    print(f"median churn: {c['fraction']:.1%} of frames, p50 {c['p50_ms']:.2f} ms, "
          f"p99 {c['p99_ms']:.2f} ms, join {c['join_ms']:.1f} ms")
    ok = c["fraction"] >= 0.99 and c["p99_ms"] <= 2 * q["p99_ms"]
    print(f"bar (>= 99 % of frames, p99 within 2x of quiet): {'met' if ok else 'NOT met'}")


if __name__ == "__main__":
    main()
