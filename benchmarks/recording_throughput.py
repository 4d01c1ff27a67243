"""Relay throughput and p99 latency with MCAP recording of every topic on, against off.

Usage::

    .venv/bin/python benchmarks/recording_throughput.py [--seconds 3] [--rounds 3]
        [--server-cpu 0] [--client-cpu 1] [--json]

The harness of ``benchmarks/relay_throughput.py`` (same publisher, subscriber, frames and
pinning: the server alone on one core, the clients on another), run against two
``fleetctl server`` processes side by side in every round:

- ``off``: no ``recording:`` section;
- ``on``: ``recording: {rules: [{topic: ".*"}]}`` into a temporary directory: every frame
  goes through the recorder's pipe to its worker process (decode, CDR, MCAP, zstd,
  disk), which inherits the server's core (and runs ``SCHED_IDLE``);
- ``on-worker-cpu``: the same with the worker moved to the clients' core.

Phase 1 (throughput): small no_drop ``std_msgs/msg/String`` frames as fast as TCP takes
them. Phase 2 (latency): paced at half of the ``off`` server's throughput (the same load
for both), p50/p99 of receive - send. For ``on`` the server's ``/metrics`` are read after
each phase, once the writer's queue is empty: messages recorded and frames dropped by the
recorder's bounds (``queue_full``: the writer thread could not keep up).
Goal (issue 16): ``on`` throughput >= 0.8x ``off``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing as mp
import os
import re
import shutil
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

import relay_throughput as rt  # the harness (benchmarks/ is the script's directory)


def run_server(cpu: int, ports: Any, record_dir: str | None, worker_cpu: int | None) -> None:
    """``fleetctl server`` on loopback; with *record_dir*, recording every topic (its
    worker process inherits the server's core, or is moved to *worker_cpu*)."""
    rt._pin(cpu)
    from fleetctl.server.app import RelayServer
    from fleetctl.server.authmap import parse_auth_map
    from fleetctl.server.config import ServerConfig
    from fleetctl.server.recording.config import RecordingConfig, RecordingRule

    auth = parse_auth_map(
        {"identities": [{"name": "bench", "cidr": "127.0.0.0/8",
                         "rules": [{"topic": "/bench/.*", "op": "both"}]}]},
        Path("bench-auth.yaml"),
    )
    db = Path(tempfile.mkdtemp()) / "fleet.db"
    recording = (None if record_dir is None
                 else RecordingConfig(Path(record_dir), (RecordingRule(".*"),)))
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=Path("-"),
                          database=db, recording=recording)

    async def main() -> None:
        async with RelayServer(config, auth) as srv:
            pid = srv.recorder.worker_pid if srv.recorder is not None else None
            if worker_cpu is not None and pid is not None:
                with contextlib.suppress(OSError):
                    os.sched_setaffinity(pid, {worker_cpu})
            ports.put(srv.port)
            await asyncio.Future()

    asyncio.run(main())


def _metrics(port: int) -> dict[str, float]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as resp:
        text = resp.read().decode()
    out = {}
    for line in text.splitlines():
        m = re.match(r'(fleetctl_recording_[a-z_]+|fleetctl_messages_in_total)'
                     r'(?:\{(?:reason|topic)="([a-z_/]+)"\})? (\S+)$', line)
        if m:
            out[m.group(1) + (f".{m.group(2)}" if m.group(2) else "")] = float(m.group(3))
    return out


def _recorder_figures(port: int) -> dict[str, float]:
    """The recorder's counters once it has recorded or dropped every frame the relay
    took (waits up to 120 s: at full load the worker yields the core to the relay)."""
    deadline = time.monotonic() + 120
    while True:
        found = _metrics(port)
        taken = found.get(f"fleetctl_messages_in_total.{rt.TOPIC}", 0)
        done = (found.get("fleetctl_recording_messages_total", 0)
                + sum(v for k, v in found.items() if k.startswith("fleetctl_recording_drop")))
        if done >= taken or time.monotonic() > deadline:
            return {"recorded": found.get("fleetctl_recording_messages_total", 0),
                    "dropped_queue_full":
                        found.get("fleetctl_recording_dropped_total.queue_full", 0),
                    "disk_bytes": found.get("fleetctl_recording_disk_bytes", 0)}
        time.sleep(0.1)  # polling the server's gauge with a deadline


def measure(variant: str, args: argparse.Namespace, rate_hz: float | None) -> dict[str, Any]:
    """One phase against a fresh server (rt.measure's steps, plus /metrics at the end)."""
    ctx = mp.get_context("spawn")
    ports, out, ready = ctx.Queue(), ctx.Queue(), ctx.Queue()
    record = variant != "off"
    record_dir = tempfile.mkdtemp(prefix="fleetctl-rec-") if record else None
    worker_cpu = args.client_cpu if variant == "on-worker-cpu" else None
    server = ctx.Process(target=run_server, daemon=True,
                         args=(args.server_cpu, ports, record_dir, worker_cpu))
    server.start()
    procs = [server]
    try:
        port = ports.get(timeout=30)
        sub = ctx.Process(target=rt.run_subscriber, daemon=True,
                          args=(args.client_cpu, port, args.seconds, True, out, ready))
        sub.start()
        procs.append(sub)
        ready.get(timeout=30)
        pub = ctx.Process(target=rt.run_publisher, daemon=True,
                          args=(args.client_cpu, port, rate_hz, args.seconds + 2, True))
        pub.start()
        procs.append(pub)
        result: dict[str, Any] = out.get(timeout=args.seconds + 30)
        pub.kill()
        pub.join()
        if record:
            result.update(_recorder_figures(port))
        return result
    finally:
        for p in procs:
            p.kill()
            p.join()
        if record_dir is not None:
            shutil.rmtree(record_dir, ignore_errors=True)


def main() -> int:
    parser = rt.base_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--variants", default="off,on,on-worker-cpu",
                        help="comma-separated subset of off,on,on-worker-cpu (off first)")
    args = parser.parse_args()

    names = tuple(args.variants.split(","))
    if names[0] != "off" or not set(names) <= {"off", "on", "on-worker-cpu"}:
        parser.error("--variants: off first, then on and/or on-worker-cpu")
    rounds: list[list[dict[str, Any]]] = []
    for _ in range(args.rounds):
        thr = {name: measure(name, args, None) for name in names}
        half = thr["off"]["rate"] / 2
        lat = {name: measure(name, args, half) for name in names}
        rows = []
        for name in names:
            row = rt._row(f"recording {name}", thr[name]["rate"], lat[name])
            if name != "off":
                row["recorded_at_max_load"] = thr[name]["recorded"]
                row["dropped_at_max_load"] = thr[name]["dropped_queue_full"]
                row["recorded_at_half_load"] = lat[name]["recorded"]
                row["dropped_at_half_load"] = lat[name]["dropped_queue_full"]
            rows.append(row)
        rounds.append(rows)
    medians = rt.median_rows(rounds)
    if args.json:
        print(json.dumps({"rounds": rounds, "median": medians}, indent=2))
        return 0
    rt.print_setup(args)
    print(f"{'server':<26} {'msgs/s':>9} {'@load':>8} {'p50 ms':>8} {'p99 ms':>8} "
          f"{'recorded/dropped (max load)':>28} {'recorded/dropped (half)':>24}")
    for label, rows in [*((f"round {i + 1}", r) for i, r in enumerate(rounds)),
                        ("median", medians)]:
        for r in rows:
            extra = ("" if "recorded_at_max_load" not in r else
                     f"{r['recorded_at_max_load']:>14.0f}/{r['dropped_at_max_load']:<13.0f}"
                     f"{r['recorded_at_half_load']:>12.0f}/{r['dropped_at_half_load']:<11.0f}")
            print(f"{label + ' ' + r['server'].split()[1]:<26} "
                  f"{r['throughput_msgs_per_s']:>9.0f} {r['latency_load_msgs_per_s']:>8.0f} "
                  f"{r['latency_p50_ms']:>8.3f} {r['latency_p99_ms']:>8.3f} {extra}")
    off = medians[0]
    for on in medians[1:]:
        ratio = on["throughput_msgs_per_s"] / off["throughput_msgs_per_s"]
        print(f"median throughput: {on['server']} {on['throughput_msgs_per_s']:.0f} msgs/s, "
              f"off {off['throughput_msgs_per_s']:.0f}: {ratio:.2f}x (goal >= 0.8x); "
              f"p99 at half load {on['latency_p99_ms']:.3f} ms (off "
              f"{off['latency_p99_ms']:.3f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
