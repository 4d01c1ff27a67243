"""Benchmark helper: a fleetctl relay plus one measuring consumer, in one process.

Run by ``benchmarks/client_link.py`` (possibly inside a network namespace)::

    python benchmarks/client_bench_peer.py --host 127.0.0.1 --auth AUTH.yaml

Prints ``{"port": N}`` once listening, then answers stdin commands with one JSON line:
``reset`` (forget samples), ``report`` (per topic: frames, bytes, first/last receive time,
latencies publish->receive in ms, seq gaps and reorders). Latency uses the frames'
``publish_time_ns`` (the sender's wall clock; same host, so one clock).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import struct
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from websockets.asyncio.client import connect

from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import load_auth_map
from fleetctl.server.config import ServerConfig
from fleetctl.wire.control import encode_subscription
from fleetctl.wire.fragments import FRAGMENT_TYPE, Reassembler
from fleetctl.wire.metadata import read_metadata

CONSUMER_TOKEN = "bench-consumer-token"


class Sink:
    """Per-topic receive statistics of the consumer."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.topics: dict[str, dict[str, Any]] = {}

    def add(self, frame: bytes, now_ns: int, size: int | None = None) -> None:
        meta = read_metadata(frame)
        t = self.topics.setdefault(meta.topic, {
            "frames": 0, "bytes": 0, "first_ns": now_ns, "last_ns": now_ns,
            "latency_ms": [], "recv_ns": [], "last_seq": None, "gaps": 0, "reorders": 0,
            "duplicates": 0, "seqs": set()})
        t["frames"] += 1
        t["bytes"] += len(frame) if size is None else size
        t["last_ns"] = now_ns
        if meta.publish_time_ns:
            t["latency_ms"].append((now_ns - meta.publish_time_ns) / 1e6)
            t["recv_ns"].append(now_ns)
        last = t["last_seq"]
        if meta.seq in t["seqs"]:
            t["duplicates"] += 1
            return
        t["seqs"].add(meta.seq)
        if last is not None and meta.seq:
            if meta.seq < last:
                t["reorders"] += 1
            elif meta.seq > last + 1:
                t["gaps"] += 1
        t["last_seq"] = meta.seq


_U16 = struct.Struct("<H").unpack_from
_U32 = struct.Struct("<I").unpack_from
_I32 = struct.Struct("<i").unpack_from


def fragment_fields(frame: bytes) -> tuple[int, int, int]:
    """``(index, count, total_bytes)`` of a Fragment frame, read from its vtable.

    Used by ``--light``: counting a message complete at its last fragment, without
    decoding or copying payloads, keeps the consumer from being the bottleneck of the
    throughput figure (the relay delivers one connection's frames in order; full
    reassembly is exercised by tests/client).
    """
    table = _U32(frame, 0)[0]
    vtable = table - _I32(frame, table)[0]
    vt_len = _U16(frame, vtable)[0]

    def u32(slot: int) -> int:
        at = vtable + 4 + 2 * slot
        off = _U16(frame, at)[0] if at + 2 <= vtable + vt_len else 0
        return _U32(frame, table + off)[0] if off else 0

    return u32(2), u32(3), u32(4)


async def consume(url: str, sink: Sink, ready: asyncio.Event, light: bool) -> None:
    reassembler = Reassembler(512 * 1024 * 1024, 30.0, max_messages=4096)
    async with connect(url, additional_headers={"Authorization": f"Bearer {CONSUMER_TOKEN}"},
                       max_size=None, compression=None, proxy=None, ping_interval=None) as ws:
        # Not /bench/bulk: the throughput figure is robot -> relay (acknowledged by
        # pongs), so no consumer can be its bottleneck.
        await ws.send(encode_subscription("/bench/(urgent|cloud|points|events|pose|scan)"))
        ready.set()
        async for message in ws:
            if isinstance(message, str):
                continue
            now = time.time_ns()
            if read_metadata(message).type == FRAGMENT_TYPE:
                if light:
                    index, count, total = fragment_fields(message)
                    if index == count - 1:
                        sink.add(message, now, size=total)
                    continue
                whole = reassembler.feed(message, time.monotonic())
                if whole is None:
                    continue
                message = whole
            sink.add(message, now)


async def commands(sink: Sink) -> None:
    loop = asyncio.get_running_loop()
    while line := (await loop.run_in_executor(None, sys.stdin.readline)).strip():
        if line == "reset":
            sink.reset()
            print(json.dumps({"ok": True}), flush=True)
        elif line == "report":
            print(json.dumps(sink.topics, default=len), flush=True)  # seqs: as a count
        elif line == "quit":
            return


async def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--auth", type=Path, required=True)
    parser.add_argument("--light", action="store_true",
                        help="count fragmented messages at their last fragment")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        config = ServerConfig(listen_host=args.host, listen_port=0, auth_map=args.auth,
                              database=Path(tmp) / "fleet.db")
        async with RelayServer(config, load_auth_map(args.auth)) as server:
            sink = Sink()
            ready = asyncio.Event()
            url = f"ws://{args.host}:{server.port}/"
            consumer = asyncio.create_task(consume(url, sink, ready, args.light))
            await asyncio.wait_for(ready.wait(), 10)
            print(json.dumps({"port": server.port}), flush=True)
            await commands(sink)
            consumer.cancel()


if __name__ == "__main__":
    asyncio.run(main())
