"""Relay throughput and added latency of ``fleetctl server`` vs a plain websockets relay.

Usage::

    .venv/bin/python benchmarks/relay_throughput.py [--seconds 3] [--rounds 3]
        [--latency-rate 25000] [--server-cpu 0] [--client-cpu 1] [--json]

Each server runs in its own process pinned to one core (``os.sched_setaffinity``); the
publisher and the subscriber are separate processes pinned to another core. Both servers
are measured with the same clients, side by side:

- ``baseline``: a plain websockets relay (``async for`` + ``send`` to every subscriber, no
  auth, no scheduling, no metadata read);
- ``fleetctl``: :class:`fleetctl.server.app.RelayServer` with an auth map, RE2
  permissions, subscriptions and per-connection outbound schedulers.

Phase 1 (throughput): the publisher sends small no_drop ``std_msgs/msg/String`` frames
(~130 bytes) as fast as TCP lets it; the subscriber counts deliveries per second.
Phase 2 (latency): the publisher paces at the bar's load, half of its 50,000 msgs/s
(``--latency-rate``; 0: half of fleetctl's measured throughput, what this phase did until
2026-12-06, when 64 KiB reads doubled that throughput and so the load of this phase); every
payload carries ``time.time_ns()`` at send (one host clock), the subscriber computes
receive - send and prints p50/p99. The publisher writes pre-built WebSocket frames (zero
masking key, legal per RFC 6455 and cheap) on the socket of a websockets sync client, so
the clients are not the bottleneck; the subscriber is a real websockets asyncio client.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing as mp
import os
import statistics
import struct
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

TOPIC = "/bench/chat"
STAMP_DIGITS = 19


def _pin(cpu: int) -> None:
    # Fewer cores than asked for: run unpinned rather than fail.
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setaffinity(0, {cpu})


# -- servers --------------------------------------------------------------------------


def run_baseline(cpu: int, ports: Any) -> None:
    """A plain websockets relay: every frame to every subscriber."""
    _pin(cpu)
    from websockets.asyncio.server import ServerConnection, serve
    from websockets.exceptions import ConnectionClosed

    subscribers: set[ServerConnection] = set()

    async def handler(ws: ServerConnection) -> None:
        if ws.request is not None and ws.request.path == "/sub":
            subscribers.add(ws)
            try:
                await ws.wait_closed()
            finally:
                subscribers.discard(ws)
            return
        async for message in ws:
            for sub in list(subscribers):
                # A subscriber leaving at the end of a phase is not an error.
                with contextlib.suppress(ConnectionClosed):
                    await sub.send(message)

    async def main() -> None:
        async with serve(handler, "127.0.0.1", 0, max_size=2**24, compression=None) as srv:
            ports.put(next(iter(srv.sockets)).getsockname()[1])
            await asyncio.Future()

    asyncio.run(main())


def run_fleetctl(cpu: int, ports: Any) -> None:
    """``fleetctl server`` with an auth map granting loopback both on /bench/.*."""
    _pin(cpu)
    from fleetctl.server.app import RelayServer
    from fleetctl.server.authmap import parse_auth_map
    from fleetctl.server.config import ServerConfig

    auth = parse_auth_map(
        {"identities": [{"name": "bench", "cidr": "127.0.0.0/8",
                         "rules": [{"topic": "/bench/.*", "op": "both"}]}]},
        Path("bench-auth.yaml"),
    )
    db = Path(tempfile.mkdtemp()) / "fleet.db"
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=Path("-"),
                          database=db)

    async def main() -> None:
        async with RelayServer(config, auth) as srv:
            ports.put(srv.port)
            await asyncio.Future()

    asyncio.run(main())


# -- clients --------------------------------------------------------------------------


def _template() -> tuple[bytes, int]:
    from fleetctl.wire.codec import default_codec

    codec = default_codec()
    cls = codec.registry.get("std_msgs/msg/String").cls
    frame = codec.encode(cls("0" * STAMP_DIGITS), "std_msgs/msg/String", TOPIC, no_drop=True)
    return frame, frame.index(b"0" * STAMP_DIGITS)


def _ws_frame(payload: bytes) -> bytes:
    # Client-to-server binary frame, FIN, masked with a zero key (payload unchanged).
    n = len(payload)
    short = n < 126
    header = struct.pack("!BB", 0x82, 0x80 | n) if short else struct.pack(
        "!BBH", 0x82, 0x80 | 126, n)
    return header + b"\0\0\0\0" + payload


def run_publisher(cpu: int, port: int, rate_hz: float | None, seconds: float,
                  fleetctl: bool) -> None:
    """Send frames for *seconds*: as fast as possible, or paced at *rate_hz*."""
    _pin(cpu)
    from websockets.sync.client import connect

    frame, offset = _template()
    head = _ws_frame(frame)
    stamp_at = len(head) - len(frame) + offset
    with connect(f"ws://127.0.0.1:{port}/pub", compression=None, max_size=None) as ws:
        if fleetctl:
            ws.recv(timeout=5)  # welcome
        send_stamped(ws.socket, head, stamp_at, seconds, rate_hz)


def send_stamped(sock: Any, head: bytes, stamp_at: int, seconds: float,
                 rate_hz: float | None) -> None:
    """Send the masked frame *head* for *seconds*, flat out or at *rate_hz*, each copy
    stamped (19 digits of ``time.time_ns()`` at *stamp_at*) just before it leaves.

    Shared with cluster_throughput.py and recording_throughput.py.
    """
    buf = bytearray(head)
    start = time.perf_counter()
    end = start + seconds
    sent = 0
    while time.perf_counter() < end:
        if rate_hz is None:
            due = 64
        else:
            # Pacing: send what is due, then yield the core to the subscriber (it
            # shares this core) instead of busy-waiting.
            due = min(64, int((time.perf_counter() - start) * rate_hz) - sent)
            if due <= 0:
                time.sleep(0.0002)
                continue
        sent += due
        chunks = []
        for _ in range(due):
            buf[stamp_at:stamp_at + STAMP_DIGITS] = b"%019d" % time.time_ns()
            chunks.append(bytes(buf))
        try:
            sock.sendall(b"".join(chunks))
        except OSError:
            return  # the measurement is over and the server went away


def median_rows(rounds: list[list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Per row position, the median of every figure over the rounds (``server`` kept)."""
    return [{key: (row[key] if key == "server" else
                   round(statistics.median(r[i][key] for r in rounds), 3))
             for key in row} for i, row in enumerate(rounds[0])]


def print_setup(args: argparse.Namespace) -> None:
    """The table's first line: frame size, pinning, phase length, rounds."""
    print(f"small messages ({len(_template()[0])} B frames), server pinned to cpu "
          f"{args.server_cpu}, clients on cpu {args.client_cpu}, {args.seconds:.0f} s/phase, "
          f"{args.rounds} rounds")


def base_parser(description: str) -> argparse.ArgumentParser:
    """The options every relay benchmark takes (seconds, cores, rounds, JSON)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--server-cpu", type=int, default=0)
    parser.add_argument("--client-cpu", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=3,
                        help="rounds of both servers; the medians are reported")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    return parser


def run_subscriber(cpu: int, port: int, seconds: float, fleetctl: bool, out: Any,
                   ready: Any) -> None:
    """Count deliveries and latencies over the measurement window."""
    _pin(cpu)

    async def main() -> None:
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed

        from fleetctl.wire.control import encode_subscription

        async with connect(f"ws://127.0.0.1:{port}/sub", compression=None,
                           max_size=None, max_queue=None) as ws:
            if fleetctl:
                await ws.recv()  # welcome
                await ws.send(encode_subscription("/bench/.*"))
                await ws.recv()  # subscribed
            ready.put(True)
            await ws.recv()
            t0 = time.perf_counter()
            count, lat = 0, []
            n = _template()[1]
            # End the window by closing the connection (no per-message wait_for: in
            # Python 3.11 it creates a task per call, which would bottleneck the client).
            asyncio.get_running_loop().call_later(seconds, ws.transport.abort)
            try:
                async for msg in ws:
                    now = time.time_ns()
                    count += 1
                    lat.append(now - int(msg[n:n + STAMP_DIGITS]))
            except ConnectionClosed:
                pass
            elapsed = time.perf_counter() - t0
            out.put({"rate": count / elapsed, "lat_ns": lat[len(lat) // 10:]})

    asyncio.run(main())


def measure(server_target: Any, fleetctl: bool, args: argparse.Namespace,
            rate_hz: float | None) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    ports, out, ready = ctx.Queue(), ctx.Queue(), ctx.Queue()
    server = ctx.Process(target=server_target, args=(args.server_cpu, ports), daemon=True)
    server.start()
    procs = [server]
    try:
        port = ports.get(timeout=30)
        sub = ctx.Process(target=run_subscriber, daemon=True,
                          args=(args.client_cpu, port, args.seconds, fleetctl, out, ready))
        sub.start()
        procs.append(sub)
        ready.get(timeout=30)
        pub = ctx.Process(target=run_publisher, daemon=True,
                          args=(args.client_cpu, port, rate_hz, args.seconds + 2, fleetctl))
        pub.start()
        procs.append(pub)
        result: dict[str, Any] = out.get(timeout=args.seconds + 30)
        return result
    finally:
        for p in procs:
            p.kill()
            p.join()


def _pct(values: list[int], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] / 1e6


def _row(name: str, throughput: float, lat: dict[str, Any]) -> dict[str, Any]:
    values = lat["lat_ns"]
    return {
        "server": name,
        "throughput_msgs_per_s": round(throughput),
        "latency_load_msgs_per_s": round(lat["rate"]),
        "latency_p50_ms": round(_pct(values, 0.50), 3),
        "latency_p99_ms": round(_pct(values, 0.99), 3),
        "latency_mean_ms": round(statistics.fmean(values) / 1e6, 3) if values else float("nan"),
    }


def main() -> int:
    parser = base_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--latency-rate", type=float, default=25_000.0,
                        help="msgs/s of the latency phase (default: half of the 50,000 bar; "
                             "0: half of fleetctl's measured throughput)")
    args = parser.parse_args()

    servers = (("baseline", run_baseline), ("fleetctl", run_fleetctl))
    rounds: list[list[dict[str, Any]]] = []
    for _ in range(args.rounds):
        # Both servers in every round, back to back, so a slow spell of the host hits
        # both; the medians over rounds are the figures.
        thr = {name: measure(target, name == "fleetctl", args, None)["rate"]
               for name, target in servers}
        half = args.latency_rate or thr["fleetctl"] / 2
        lat = {name: measure(target, name == "fleetctl", args, half)
               for name, target in servers}
        rounds.append([_row(name, thr[name], lat[name]) for name, _ in servers])
    medians = median_rows(rounds)
    if args.json:
        print(json.dumps({"rounds": rounds, "median": medians}, indent=2))
        return 0
    print_setup(args)
    print(f"{'server':<16} {'msgs/s':>10} {'@load msgs/s':>13} {'p50 ms':>8} {'p99 ms':>8}")
    for label, rows in [*((f"round {i + 1}", r) for i, r in enumerate(rounds)),
                        ("median", medians)]:
        for r in rows:
            print(f"{label + ' ' + r['server']:<16} {r['throughput_msgs_per_s']:>10.0f} "
                  f"{r['latency_load_msgs_per_s']:>13.0f} {r['latency_p50_ms']:>8.3f} "
                  f"{r['latency_p99_ms']:>8.3f}")
    ratio = medians[1]["throughput_msgs_per_s"] / medians[0]["throughput_msgs_per_s"]
    added = medians[1]["latency_p99_ms"] - medians[0]["latency_p99_ms"]
    print(f"median throughput: fleetctl {medians[1]['throughput_msgs_per_s']:.0f} msgs/s "
          f"(bar: 50,000), {ratio:.2f}x the plain relay")
    load = medians[1]["latency_load_msgs_per_s"]
    print(f"median p99 at {load:.0f} msgs/s: {medians[1]['latency_p99_ms']:.3f} ms "
          "(bar: < 2 ms at 25,000); "
          f"added vs baseline: {added:.3f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
