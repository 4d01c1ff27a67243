"""The software latency floor, fleetctl against zenoh, on loopback (issue 19: where does the
time go?).

Usage::

    .venv/bin/python benchmarks/peer_latency.py [--seconds 15] [--json FILE]
        [--python-hop] [--compiled-hop] [--consumers N] [--rounds K]

No network between the parts (everything on 127.0.0.1, no tc, no tunnel): what is left is
each stack's own per-message path. The e2e ``peer`` load (``python -m fleetctl.e2e.load
--profile peer``: 720-beam scan at 10 Hz, pose at 20 Hz, each message stamped with its ROS
publish time) goes, one stack after the other:

- **fleetctl**: ``fleetctl client`` (a real process: rclpy raw subscription, encode, link)
  -> ``fleetctl server`` (:class:`fleetctl.server.app.RelayServer`, real process) -> a
  WebSocket consumer in this process that takes each frame in the read that brought it, as
  the e2e consumer does (:mod:`fleetctl.frame_sink`; ``--recv-consumer`` adds a run whose
  consumer reads with ``async for`` instead, the e2e consumer's way before 2026-11-29). It
  also reads each frame's metadata ``publish_time_ns`` (when the client took the message
  from ROS) to split the path into *ROS -> client* (DDS, rclpy, the hop onto the client's
  loop) and *client -> consumer* (encode, schedule, send, relay, receive);
- **zenoh-default** and **zenoh-best**: the e2e zenoh bridge -> zenoh router -> zenoh
  consumer (:mod:`fleetctl.e2e.zenohpeer`, same settings as the e2e ``peer`` scenario).

- **python-hop** and **compiled-hop** (``--python-hop``, ``--compiled-hop``): fleetctl's
  client, load and consumer as above, with a probe in the relay's place that does only
  the relay's data path (parse, unmask, inflate, one frame written to every receiver in
  the read; no authentication, sessions or routing): ``benchmarks/python_hop.py`` in the
  leanest asyncio Python, ``benchmarks/compiled_hop`` in Rust (built with cargo on first
  use). They answer "what would it take": how much of fleetctl's gap to zenoh is the
  relay being Python (docs/benchmarks.md).

``--consumers N`` puts N consumers in one process for every stack (the fan-out case, as
the e2e ``peer-fanout``); ``--rounds K`` runs every stack K times, alternating, so that
the host's drift shows as spread instead of as a difference between stacks.

Printed: p50 and p99 per topic and stack over ``--seconds`` (after a 3 s warm-up), and
the split for fleetctl's client. Latency is consumer receipt minus the ROS publish stamp
(one host clock).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hashlib
import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
PY = sys.executable
ROBOT_TOKEN = "peer-latency-robot"
VIEWER_TOKEN = "peer-latency-viewer"
WARMUP_S = 3.0
TOPICS = ("/robot1/scan", "/robot1/pose")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _start(argv: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(argv, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT,
                            start_new_session=True)


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)


def _stats(values: list[float]) -> dict[str, float]:
    if not values:
        return {"n": 0, "p50_ms": float("nan"), "p99_ms": float("nan")}
    ordered = sorted(values)
    return {"n": len(ordered), "p50_ms": statistics.median(ordered),
            "p99_ms": ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))]}


def _fleetctl_files(work: Path, port: int) -> tuple[Path, Path]:
    import yaml

    from fleetctl.e2e import profiles

    def sha(token: str) -> str:
        return hashlib.sha256(token.encode()).hexdigest()

    (work / "auth.yaml").write_text(json.dumps({"version": 1, "identities": [
        {"name": "robot1", "token_sha256": sha(ROBOT_TOKEN),
         "rules": [{"topic": "/robot1/.*", "op": "send"}]},
        {"name": "viewer", "token_sha256": sha(VIEWER_TOKEN),
         "rules": [{"topic": ".*", "op": "receive"}]},
    ]}))
    server = work / "server.yaml"
    server.write_text(yaml.safe_dump({"listen_host": "127.0.0.1", "listen_port": port,
                                      "auth_map": str(work / "auth.yaml"),
                                      "database": str(work / "fleet.db")}))
    (work / "token").write_text(ROBOT_TOKEN)
    cfg = profiles.client_config(profiles.profile("peer"), f"ws://127.0.0.1:{port}/")
    cfg["token_file"] = str(work / "token")
    client = work / "client.yaml"
    client.write_text(yaml.safe_dump(cfg))
    return server, client


async def _fleetctl_consumers(port: int, seconds: float, sink: bool,
                              count: int) -> dict[str, list[tuple[float, ...]]]:
    """*count* consumers in this process (one event loop, as the e2e consumer's
    ``--count``), their rows together."""
    out: dict[str, list[tuple[float, ...]]] = {}
    for got in await asyncio.gather(*(_fleetctl_consumer(port, seconds, sink)
                                      for _ in range(count))):
        for topic, rows in got.items():
            out.setdefault(topic, []).extend(rows)
    return out


async def _fleetctl_consumer(port: int, seconds: float,
                             sink: bool) -> dict[str, list[tuple[float, ...]]]:
    from websockets.asyncio.client import connect

    from fleetctl.e2e.consumer import (
        REASSEMBLY_MAX_BYTES,
        REASSEMBLY_TIMEOUT_S,
        ConsumerConnection,
    )
    from fleetctl.wire.codec import default_codec
    from fleetctl.wire.control import encode_subscription
    from fleetctl.wire.fragments import Reassembler

    codec = default_codec()
    # The client may split a scan (before its first rate sample, or on a slow rate reading):
    # a message counts when it is whole.
    reassembler = Reassembler(REASSEMBLY_MAX_BYTES, REASSEMBLY_TIMEOUT_S)
    out: dict[str, list[tuple[float, ...]]] = {}
    deadline = time.monotonic() + 60
    while True:
        try:
            ws = await connect(f"ws://127.0.0.1:{port}/", max_size=None,
                               additional_headers={"Authorization": f"Bearer {VIEWER_TOKEN}"},
                               create_connection=ConsumerConnection)
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.1)  # polling the server's start, bounded by the deadline
    assert isinstance(ws, ConsumerConnection)
    async with ws:
        await ws.send(encode_subscription("/robot1/.*"))
        start = time.monotonic()
        measure_from = start + WARMUP_S
        end = measure_from + seconds

        def in_read(frame: bytes) -> bool:  # the e2e consumer's way (fleetctl.frame_sink)
            now = time.time_ns()
            if time.monotonic() < end:
                _record(frame, now, measure_from, codec, reassembler, out)
            return True

        if sink:
            ws.frame_sink = in_read
        # One deadline for the whole window, not a wait_for per frame: that would add a task
        # and a timer to every receive, which the e2e consumer (``async for``) does not pay.
        with contextlib.suppress(TimeoutError):  # the window ended while no frame came
            async with asyncio.timeout(end - start):
                async for frame in ws:
                    now = time.time_ns()
                    ws.message_handled()
                    if time.monotonic() >= end:
                        break
                    _record(frame, now, measure_from, codec, reassembler, out)
    return out


def _record(frame: str | bytes, now: int, measure_from: float, codec: Any, reassembler: Any,
            out: dict[str, list[tuple[float, ...]]]) -> None:
    """Add one received frame's three latencies to *out* (a whole, measured message)."""
    from fleetctl.e2e.payloads import read_stamp
    from fleetctl.wire.fragments import FRAGMENT_TYPE
    from fleetctl.wire.metadata import read_metadata

    if not isinstance(frame, bytes):
        return
    if read_metadata(frame).type == FRAGMENT_TYPE:
        whole = reassembler.feed(frame, time.monotonic())
        if whole is None:
            return
        frame = whole
    if time.monotonic() < measure_from:
        return
    meta, msg = codec.decode(frame)
    if meta.topic not in TOPICS:  # the client's own /status
        return
    stamp = read_stamp(msg)
    out.setdefault(meta.topic, []).append((
        (now - stamp.publish_time_ns) / 1e6,
        (meta.publish_time_ns - stamp.publish_time_ns) / 1e6,
        (now - meta.publish_time_ns) / 1e6))


def run_fleetctl(work: Path, env: dict[str, str], seconds: float, sink: bool = True,
                 hop: list[str] | None = None, consumers: int = 1) -> dict[str, Any]:
    """The fleetctl path; *hop*: a probe's command in the relay's place (its address is
    appended)."""
    port = _free_port()
    server_cfg, client_cfg = _fleetctl_files(work, port)
    fleetctl = str(Path(PY).parent / "fleetctl")
    relay = ([*hop, f"127.0.0.1:{port}"] if hop is not None
             else [fleetctl, "server", "--config", str(server_cfg)])
    procs = [
        _start(relay, env, work / "server.log"),
        _start([fleetctl, "client", "--config", str(client_cfg)], env, work / "client.log"),
        _start([PY, "-m", "fleetctl.e2e.load", "--profile", "peer"], env, work / "load.log"),
    ]
    try:
        got = asyncio.run(_fleetctl_consumers(port, seconds, sink, consumers))
    finally:
        _stop(procs)
    return {topic: {"total": _stats([r[0] for r in rows]),
                    "ros_to_client": _stats([r[1] for r in rows]),
                    "client_to_consumer": _stats([r[2] for r in rows])}
            for topic, rows in sorted(got.items())}


def run_zenoh(work: Path, env: dict[str, str], seconds: float, settings: str,
              consumers: int = 1) -> dict[str, Any]:
    from fleetctl.e2e.samples import load

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    zp = [PY, "-m", "fleetctl.e2e.zenohpeer"]
    out = work / f"zenoh-{settings}"
    out.mkdir()
    router = _start([*zp, "router", "--settings", settings, "--listen", endpoint], env,
                    work / f"router-{settings}.log")
    procs = [router]
    try:
        _wait(lambda: "listening" in (work / f"router-{settings}.log").read_text(), 30,
              "the zenoh router")
        procs.append(_start([*zp, "consumer", "--settings", settings, "--connect", endpoint,
                             "--name", "z", "--count", str(consumers), "--out", str(out)],
                            env, work / f"consumer-{settings}.log"))
        _wait(lambda: (out / f"z-{consumers - 1}.ready").exists(), 30, "the zenoh consumers")
        procs.append(_start([*zp, "bridge", "--settings", settings, "--connect", endpoint],
                            env, work / f"bridge-{settings}.log"))
        procs.append(_start([PY, "-m", "fleetctl.e2e.load", "--profile", "peer"], env,
                            work / f"load-{settings}.log"))
        _wait(lambda: (out / "z-0.jsonl").exists() and (out / "z-0.jsonl").stat().st_size > 0,
              60, "zenoh samples")
        start_ns = time.time_ns() + int(WARMUP_S * 1e9)
        _wait(lambda: time.time_ns() > start_ns + int(seconds * 1e9), seconds + 30,
              "the measuring window")
    finally:
        _stop(procs)
    samples = []
    for i in range(consumers):
        text = (out / f"z-{i}.jsonl").read_text()
        samples += [s for s in load(text[: text.rfind("\n") + 1]) if s.recv_time_ns >= start_ns]
    by: dict[str, list[float]] = {}
    for s in samples:
        by.setdefault(s.topic, []).append(s.latency_ms)
    return {topic: {"total": _stats(v)} for topic, v in sorted(by.items())}


def build_compiled_hop() -> Path:
    """``cargo build --release`` of benchmarks/compiled_hop; the binary's path."""
    crate = HERE / "compiled_hop"
    if shutil.which("cargo") is None:
        raise SystemExit("--compiled-hop needs cargo (the Rust toolchain) on PATH")
    subprocess.run(["cargo", "build", "--release", "--quiet", "--manifest-path",
                    str(crate / "Cargo.toml")], check=True)
    return crate / "target" / "release" / "fleetctl-compiled-hop"


def _wait(cond: Any, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise SystemExit(f"timed out waiting for {what}")
        time.sleep(0.05)  # polling interval of a deadline-bounded wait


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--recv-consumer", action="store_true",
                        help="also run fleetctl with a consumer that reads with recv() "
                             "(async for) instead of in the read (fleetctl.frame_sink)")
    parser.add_argument("--compiled-hop", action="store_true",
                        help="also run fleetctl's client and consumer with the relay's data "
                             "path compiled in the relay's place (benchmarks/compiled_hop, "
                             "built with cargo)")
    parser.add_argument("--python-hop", action="store_true",
                        help="also run them with the same probe in the leanest asyncio "
                             "Python (benchmarks/python_hop.py)")
    parser.add_argument("--consumers", type=int, default=1,
                        help="consumers per stack, in one process (the fan-out case)")
    parser.add_argument("--rounds", type=int, default=1,
                        help="repeat every stack's run, alternating (side by side)")
    args = parser.parse_args()
    if args.consumers < 1 or args.rounds < 1:
        parser.error("--consumers and --rounds must be at least 1")
    hops: dict[str, list[str]] = {}
    if args.python_hop:
        hops["python-hop"] = [PY, str(HERE / "python_hop.py")]
    if args.compiled_hop:
        hops["compiled-hop"] = [str(build_compiled_hop())]
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    env = {**os.environ, "PYTHONPATH": str(HERE.parent),
           "ROS_DOMAIN_ID": str(100 + os.getpid() % 100),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "PYTHONUNBUFFERED": "1"}
    results: dict[str, Any] = {}
    for round_no in range(args.rounds):
        tag = f" #{round_no + 1}" if args.rounds > 1 else ""
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            n = args.consumers
            results[f"fleetctl{tag}"] = run_fleetctl(work, env, args.seconds, consumers=n)
            if args.recv_consumer:
                results[f"fleetctl-recv{tag}"] = run_fleetctl(work, env, args.seconds,
                                                              sink=False, consumers=n)
            for name, argv in hops.items():
                results[f"{name}{tag}"] = run_fleetctl(work, env, args.seconds, hop=argv,
                                                       consumers=n)
            for settings in ("default", "best"):
                results[f"zenoh-{settings}{tag}"] = run_zenoh(work, env, args.seconds,
                                                              settings, consumers=n)
    print(f"loopback, {args.seconds:g} s after {WARMUP_S:g} s warm-up, {args.consumers} "
          "consumer(s); latency = consumer receipt - ROS publish stamp")
    print(f"  {'stack':18s} {'topic':16s} {'n':>5s} {'p50 ms':>8s} {'p99 ms':>8s}")
    for stack, topics in results.items():
        for topic, parts in topics.items():
            st = parts["total"]
            print(f"  {stack:18s} {topic:16s} {st['n']:5d} {st['p50_ms']:8.3f} "
                  f"{st['p99_ms']:8.3f}")
    print("  fleetctl split (p50 ms): ROS -> client intake | client intake -> consumer")
    for stack in (k for k in results if not k.startswith("zenoh")):
        for topic, parts in results[stack].items():
            print(f"    {stack:18s} {topic:16s} {parts['ros_to_client']['p50_ms']:8.3f} | "
                  f"{parts['client_to_consumer']['p50_ms']:8.3f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
