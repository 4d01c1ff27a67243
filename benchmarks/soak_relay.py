"""Relay soak: does a relay under fleet-like churn hold memory, fds, tasks or state?

Usage::

    .venv/bin/python benchmarks/soak_relay.py [--minutes 5] [--sample-s 10]
        [--warmup-s 60] [--robots 6] [--viewers 4] [--foxglove 2] [--junk 2]
        [--session-expiry-s 60] [--no-record] [--tracemalloc] [--json]

Three processes: the relay (:class:`RelayServer`, default limits but
``session_expiry_s``, recording on unless ``--no-record``; pinned to core 0), the churn
(one asyncio process, core 1), and this one, which samples the relay every
``--sample-s``: RSS, open fds and threads from ``/proc/<pid>``, a few gauges of
``GET /metrics`` (and its size), and from inside the relay process its asyncio task
count, ``gc`` object count and the length of every dict/set/list/deque reachable from
the server's own objects (``core.subs._receivers``, ``registry._robots``, ...: found by
walking attributes, so a new table is sampled without naming it here).

What the churn does, each actor in a loop with random lifetimes:

- ``--robots`` robots, each from its own loopback address (an address identity, so the
  registry sees them), a new robot name each round (``r<slot>n<round>``), session named
  after the robot and subscribed to its ``goal`` (so the session outlives the connection
  for ``--session-expiry-s``): a latched map at connect (``--map-kib``, 256), an 8 KiB
  "scan" at 10 Hz, pose and TF (~200 B) at 20 Hz, a small CompressedVideo at 10 Hz, a
  RobofleetStatus at 1 Hz;
  then a clean close, an abrupt TCP reset (SO_LINGER 0), or a reset and a resume (the
  next round keeps the name: the session is taken up again);
- ``--viewers`` token viewers, half with a named session (resumed next round), changing
  regexes (a robot, ``.*/pose``, ``.*``, literals), subscribe/unsubscribe, a no_drop goal
  to a recent robot name with each change (an offline robot's session mailboxes it), and
  every fifth round a slow reader that subscribes to ``.*`` and stops reading;
- ``--foxglove`` Foxglove clients (Bearer token + ``foxglove.websocket.v1``): advertise,
  subscribe to a few channels, unsubscribe, leave (clean or reset);
- ``--junk`` pests: connections that never authenticate (the relay aborts them after
  ``auth_timeout_s``), bad tokens, bad frames, raw TCP that stops mid-handshake,
  ``/metrics`` and ``/robots`` scrapes.

Printed: a table of the samples, then for each series its value at the end of warm-up
and at the end, growth per hour fitted (least squares) over the samples after warm-up
and over the last third, and a verdict per series (``flat``, ``plateau``: grew, then not
in the last third, ``to cap``: still growing toward a bound :data:`CAPS` names, or
``GROWS``: no known bound). ``--tracemalloc`` also prints the allocation sites that
grew most between the end of warm-up (or ``--snapshot-s``) and the end (slows the relay).
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import gc
import json
import multiprocessing as mp
import os
import random
import socket
import statistics
import struct
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

VIEWER = "soak-viewer-token"
FOXGLOVE = "soak-foxglove-token"
FIRST_ROBOT_ADDRESS = 10  # robot slot k connects from 127.0.0.(10 + k)
SUBPROTOCOL = "foxglove.websocket.v1"
# /metrics gauges sampled (first value of each name, or the number of its series).
GAUGES = ("fleetctl_connections_open", "fleetctl_latched_bytes", "fleetctl_latched_messages",
          "fleetctl_standby_connections")


def _pin(cpu: int) -> None:
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setaffinity(0, {cpu})


# -- the relay process ------------------------------------------------------------------


def _auth_yaml(path: Path, robots: int) -> None:
    from fleetctl.tokens import hash_token

    lines = ["version: 1", "identities:"]
    for name, token in (("viewer", VIEWER), ("foxglove", FOXGLOVE)):
        lines += [f"  - name: {name}", f"    token_sha256: {hash_token(token)}",
                  "    rules:", "      - {topic: '.*', op: receive}",
                  "      - {topic: '/[^/]+/goal', op: send}"]
    for k in range(robots):
        lines += [f"  - name: slot{k}", f"    ip: 127.0.0.{FIRST_ROBOT_ADDRESS + k}",
                  "    rules:", "      - {topic: '.*', op: both}"]
    path.write_text("\n".join(lines) + "\n")


def _walk(obj: Any, prefix: str, out: dict[str, int], seen: set[int], depth: int) -> None:
    """Record len() of every container attribute reachable from *obj* (fleetctl objects
    only, *depth* levels down)."""
    if id(obj) in seen:
        return
    seen.add(id(obj))
    names = list(getattr(obj, "__dict__", {}))
    for cls in type(obj).__mro__:
        names += [n for n in getattr(cls, "__slots__", ()) if isinstance(n, str)]
    for name in names:
        value = getattr(obj, name, None)
        if isinstance(value, (dict, set, frozenset, list, collections.deque)):
            if name != "peers" or prefix != "core.":  # counted below, per peer
                out[prefix + name] = len(value)
        elif (depth > 0 and type(value).__module__.startswith("fleetctl")
              and not isinstance(value, type)):
            _walk(value, f"{prefix}{name}.", out, seen, depth - 1)


def _sizes(server: Any) -> dict[str, int]:
    loop: Any = asyncio.get_running_loop()
    out: dict[str, int] = {"tasks": len(asyncio.all_tasks()), "gc_objects": len(gc.get_objects()),
                           "loop_timers": len(getattr(loop, "_scheduled", ()))}
    seen: set[int] = set()
    _walk(server, "", out, seen, 4)
    out["core.peers"] = len(server.core.peers)
    per_peer: dict[str, int] = {}
    for peer in list(server.core.peers.values()):
        _walk(peer, "peer.", per_peer, set(seen), 2)  # shared objects counted once above
    out.update({f"sum({k})": v for k, v in per_peer.items()})
    return out


def _top_growth(before: Any, after: Any) -> list[str]:
    stats = after.compare_to(before, "lineno")
    return [str(s) for s in stats[:15]]


def run_server(cpu: int, directory: str, args: argparse.Namespace, ports: Any,
               samples: Any, requests: Any) -> None:
    """The relay until terminated; answers each sample request with its sizes."""
    _pin(cpu)
    import dataclasses

    from fleetctl.server.app import RelayServer
    from fleetctl.server.config import ServerConfig, ServerLimits
    from fleetctl.server.recording.config import RecordingConfig, RecordingRule

    if args.mmap_threshold_kib:  # glibc: larger blocks mmapped, returned on free
        import ctypes
        ctypes.CDLL("libc.so.6").mallopt(-3, args.mmap_threshold_kib * 1024)  # M_MMAP_THRESHOLD
    if args.tracemalloc:
        import tracemalloc
        tracemalloc.start(4)
    base = Path(directory)
    _auth_yaml(base / "auth.yaml", args.robots)
    recording = None if args.no_record else RecordingConfig(
        directory=base / "rec", rules=(RecordingRule("/.*/(status|pose)"),),
        max_file_bytes=8 << 20, max_file_duration_s=120.0, max_total_bytes=32 << 20)
    limits = dataclasses.replace(ServerLimits(), session_expiry_s=args.session_expiry_s)
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=base / "auth.yaml",
                          database=base / "fleet.db", limits=limits, recording=recording)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        snapshot: Any = None
        async with RelayServer(config) as server:
            ports.put(server.port)
            while True:
                what = await loop.run_in_executor(None, requests.get)
                if what == "snapshot" and args.tracemalloc:
                    snapshot = tracemalloc.take_snapshot()
                elif what == "growth" and args.tracemalloc and snapshot is not None:
                    samples.put(_top_growth(snapshot, tracemalloc.take_snapshot()))
                    continue
                samples.put(_sizes(server))

    asyncio.run(main())


# -- the churn ---------------------------------------------------------------------------


class Frames:
    """Frame bytes per robot name, encoded once (the relay does not look at seq)."""

    def __init__(self) -> None:
        from fleetctl.wire.codec import default_codec

        self.codec = default_codec()
        self.string = self.codec.registry.get("std_msgs/msg/String").cls

    def text(self, topic: str, size: int, *, latched: bool = False,
             no_drop: bool = False) -> bytes:
        return self.codec.encode(self.string("x" * size), "std_msgs/msg/String", topic,
                                 latched=latched, no_drop=no_drop)

    def video(self, topic: str, size: int) -> bytes:
        import numpy as np

        name = "foxglove_msgs/msg/CompressedVideo"
        stamp_cls = self.codec.registry.get("builtin_interfaces/msg/Time").cls
        msg = self.codec.registry.get(name).cls(stamp_cls(0, 0), "cam",
                                                np.zeros(size, dtype=np.uint8), "h264")
        return self.codec.encode(msg, name, topic)

    def status(self, robot: str) -> bytes:
        from fleetctl.wire.control import encode_status

        return encode_status(robot, status="ok", is_ok=True, battery_level=0.5,
                             codec=self.codec)


def _reset(ws: Any) -> None:
    """An abrupt close: RST, no close frame (a robot losing power, a NAT dropping)."""
    sock = ws.transport.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    ws.transport.abort()


async def _drain(ws: Any) -> None:
    with contextlib.suppress(Exception):
        async for _ in ws:
            pass


async def _end(ws: Any, how: str, counts: collections.Counter[str]) -> None:
    counts[f"end_{how}"] += 1
    if how == "clean":
        with contextlib.suppress(Exception):
            await asyncio.wait_for(ws.close(), 5)
    else:
        _reset(ws)


async def robot(slot: int, port: int, frames: Frames, map_bytes: int, stop: asyncio.Event,
                counts: collections.Counter[str]) -> None:
    from websockets.asyncio.client import connect

    from fleetctl.wire.control import encode_subscription

    rounds, name = 0, ""
    while not stop.is_set():
        rounds += 1
        how = random.choice(("clean", "reset", "resume"))
        if not name or counts.get(f"resume{slot}") != 1:
            name = f"r{slot}n{rounds}"
        counts[f"resume{slot}"] = int(how == "resume")
        t = f"/{name}"
        scan, pose, tf = frames.text(f"{t}/scan", 8192), frames.text(f"{t}/pose", 200), \
            frames.text(f"{t}/tf", 200)
        video, status = frames.video(f"{t}/camera", 2048), frames.status(name)
        the_map = frames.text(f"{t}/map", map_bytes, latched=True)
        try:
            async with connect(f"ws://127.0.0.1:{port}/", max_size=None, open_timeout=10,
                               local_addr=(f"127.0.0.{FIRST_ROBOT_ADDRESS + slot}", 0),
                               additional_headers={"X-Fleetctl-Session": name}) as ws:
                counts["robot_connects"] += 1
                reader = asyncio.create_task(_drain(ws))
                await ws.send(encode_subscription(f"{t}/goal"))  # kept by its session
                await ws.send(the_map)
                until = time.monotonic() + random.uniform(4, 12)
                tick = 0
                while time.monotonic() < until and not stop.is_set() and not reader.done():
                    tick += 1  # 20 Hz: pose and TF each tick, scan and video every other
                    batch = [pose, tf] + ([scan, video] if tick % 2 else [])
                    batch += [status] if tick % 20 == 0 else []
                    for frame in batch:
                        await ws.send(frame)
                    counts["robot_frames"] += len(batch)
                    await asyncio.sleep(0.05)  # the robot's publish rate
                await _end(ws, "clean" if how == "clean" else "reset", counts)
                reader.cancel()
        except Exception as exc:  # a refused or cut connection: count it, go on
            counts[f"robot_error_{type(exc).__name__}"] += 1
            await asyncio.sleep(0.5)


def _viewer_patterns(robots: int) -> list[str]:
    slot = random.randrange(robots)
    return random.sample([f"/r{slot}n.*", ".*/pose", ".*", f"/r{slot}n1/scan", ".*/camera",
                          "/r[0-9]+n[0-9]+/status", f"/r{slot}n2/map"], 3)


async def viewer(slot: int, port: int, robots: int, frames: Frames, stop: asyncio.Event,
                 counts: collections.Counter[str]) -> None:
    from websockets.asyncio.client import connect

    from fleetctl.wire.control import encode_subscription

    rounds = 0
    while not stop.is_set():
        rounds += 1
        slow = rounds % 5 == 0
        headers = {"Authorization": f"Bearer {VIEWER}"}
        if slot % 2 == 0:
            headers["X-Fleetctl-Session"] = f"viewer{slot}"
        try:
            async with connect(f"ws://127.0.0.1:{port}/", max_size=None, open_timeout=10,
                               additional_headers=headers, max_queue=4) as ws:
                counts["viewer_connects"] += 1
                if slow:  # subscribes to everything, then never reads: the relay drops
                    await ws.send(encode_subscription(".*"))
                    counts["slow_readers"] += 1
                    await asyncio.sleep(random.uniform(5, 10))  # its life, unread
                    _reset(ws)
                    continue
                reader = asyncio.create_task(_drain(ws))
                until = time.monotonic() + random.uniform(4, 12)
                held: list[str] = []
                while time.monotonic() < until and not stop.is_set():
                    for pattern in held:
                        await ws.send(encode_subscription(pattern, False))
                    held = _viewer_patterns(robots)
                    for pattern in held:
                        await ws.send(encode_subscription(pattern))
                    counts["viewer_changes"] += 1
                    goal = f"/r{random.randrange(robots)}n{random.randint(1, rounds + 2)}/goal"
                    await ws.send(frames.text(goal, 100, no_drop=True))
                    counts["goals"] += 1
                    if random.random() < 0.2:
                        await ws.send(b"\x00not a frame")
                        counts["bad_frames"] += 1
                    await asyncio.sleep(random.uniform(0.5, 2))  # a user's pace
                await _end(ws, random.choice(("clean", "reset")), counts)
                reader.cancel()
        except Exception as exc:
            counts[f"viewer_error_{type(exc).__name__}"] += 1
            await asyncio.sleep(0.5)


async def foxglove(port: int, stop: asyncio.Event, counts: collections.Counter[str]) -> None:
    from websockets.asyncio.client import connect

    while not stop.is_set():
        try:
            async with connect(f"ws://127.0.0.1:{port}/", max_size=None, open_timeout=10,
                               subprotocols=[SUBPROTOCOL], compression=None,
                               additional_headers={"Authorization": f"Bearer {FOXGLOVE}"}) as ws:
                counts["foxglove_connects"] += 1
                channels: dict[int, str] = {}
                subscribed: list[int] = []
                until = time.monotonic() + random.uniform(4, 10)
                next_change = 0.0
                while time.monotonic() < until and not stop.is_set():
                    with contextlib.suppress(TimeoutError):
                        message = await asyncio.wait_for(ws.recv(), 0.2)
                        if isinstance(message, str):
                            data = json.loads(message)
                            if data["op"] == "advertise":
                                channels.update({c["id"]: c["topic"] for c in data["channels"]})
                            elif data["op"] == "unadvertise":
                                for c in data["channelIds"]:
                                    channels.pop(c, None)
                    if channels and time.monotonic() > next_change:
                        next_change = time.monotonic() + 1.0
                        if subscribed:
                            await ws.send(json.dumps({"op": "unsubscribe",
                                                      "subscriptionIds": subscribed}))
                        picks = random.sample(sorted(channels), min(3, len(channels)))
                        subscribed = [random.randrange(1 << 30) for _ in picks]
                        pairs = zip(subscribed, picks, strict=True)
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": s, "channelId": c} for s, c in pairs]}))
                        counts["foxglove_changes"] += 1
                await _end(ws, random.choice(("clean", "reset")), counts)
        except Exception as exc:
            counts[f"foxglove_error_{type(exc).__name__}"] += 1
            await asyncio.sleep(0.5)


async def junk(port: int, stop: asyncio.Event, counts: collections.Counter[str]) -> None:
    from websockets.asyncio.client import connect

    url = f"ws://127.0.0.1:{port}/"
    while not stop.is_set():
        kind = random.choice(("silent", "bad_token", "half_handshake", "scrape", "token_frame"))
        counts[f"junk_{kind}"] += 1
        try:
            if kind == "silent":  # authenticates never; the relay aborts it (auth_timeout_s)
                ws = await connect(url, open_timeout=10)
                await _drain(ws)
            elif kind == "bad_token":
                async with connect(url, open_timeout=10, additional_headers={
                        "Authorization": "Bearer wrong"}) as ws:
                    await _drain(ws)
            elif kind == "token_frame":  # a first token frame, a bad frame, then a reset
                async with connect(url, open_timeout=10) as ws:
                    await ws.send(json.dumps({"token": VIEWER}))
                    await ws.send(b"\xff" * 64)
                    await ws.send("{not json")
                    _reset(ws)
            elif kind == "half_handshake":  # TCP open, half a request, then a reset
                _, writer = await asyncio.open_connection("127.0.0.1", port)
                writer.write(b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\n")
                await writer.drain()
                await asyncio.sleep(random.uniform(0.5, 3))
                sock = writer.get_extra_info("socket")
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                writer.transport.abort()
            else:
                for path in ("/metrics", "/robots"):
                    await asyncio.to_thread(_get, port, path)
        except Exception as exc:
            counts[f"junk_error_{type(exc).__name__}"] += 1
        await asyncio.sleep(random.uniform(0.1, 1))


def _get(port: int, path: str) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10) as answer:
        return str(answer.read().decode())


def run_churn(cpu: int, port: int, args: argparse.Namespace, stop: Any, results: Any) -> None:
    _pin(cpu)
    counts: collections.Counter[str] = collections.Counter()

    async def main() -> None:
        done = asyncio.Event()
        frames = Frames()
        tasks = [asyncio.create_task(robot(k, port, frames, args.map_kib * 1024, done,
                                                   counts))
                 for k in range(args.robots)]
        tasks += [asyncio.create_task(viewer(k, port, args.robots, frames, done, counts))
                  for k in range(args.viewers)]
        tasks += [asyncio.create_task(foxglove(port, done, counts)) for _ in range(args.foxglove)]
        tasks += [asyncio.create_task(junk(port, done, counts)) for _ in range(args.junk)]
        while not stop.is_set():  # polling a cross-process event: not synchronization
            await asyncio.sleep(0.2)
        done.set()
        await asyncio.wait(tasks, timeout=20)
        for task in tasks:
            task.cancel()

    asyncio.run(main())
    results.put({k: v for k, v in counts.items() if not k.startswith("resume")})


# -- sampling ------------------------------------------------------------------------------


def _proc(pid: int) -> dict[str, int]:
    status = Path(f"/proc/{pid}/status").read_text()
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    children = 0  # the recorder's worker process
    for task in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(OSError):
            for child in Path(f"/proc/{pid}/task/{task}/children").read_text().split():
                children += _rss_kib(int(child))
    return {"rss_kib": int(fields["VmRSS"].split()[0]), "threads": int(fields["Threads"]),
            "fds": len(os.listdir(f"/proc/{pid}/fd")), "children_rss_kib": children}


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _disk(directory: Path) -> dict[str, int]:
    """KiB of the registry database (robots, sessions) and of the recordings."""
    def kib(paths: Any) -> int:
        return sum(p.stat().st_size for p in paths if p.is_file()) // 1024

    return {"db_kib": kib(directory.glob("fleet.db*")),
            "recordings_kib": kib((directory / "rec").glob("*"))}


def _metrics(port: int) -> dict[str, int]:
    text = _get(port, "/metrics")
    out = {"metrics_lines": text.count("\n")}
    for line in text.splitlines():
        name, _, value = line.partition(" ")
        if name in GAUGES and name not in out:
            out[name.removeprefix("fleetctl_")] = int(float(value))
    return out


# What bounds the tables that grow with new topics and robot names (the soak's new names
# reach these caps after hours, not minutes): series name prefix -> its bound.
CAPS = {
    "core.subs._cache": "16,384 topics, then cleared (subscriptions.MAX_CACHED_TOPICS)",
    "sum(peer.perms.": "16,384 topics per identity set, then cleared (permissions)",
    "sum(peer.session.perms.": "16,384 topics per identity set, then cleared (permissions)",
    "recorder.rules._cache": "16,384 (topic, identity set), then cleared (recording/rules)",
    "core.catalog._ids": "4,096 channels; ids of ended ones forgotten when full (foxglove)",
    "core.latched.": "4,096 (sender, topic) and latched_bytes (64 MiB), LRU eviction",
    "latched_": "4,096 (sender, topic) and latched_bytes (64 MiB), LRU eviction",
    "metrics.": "2,000 topic labels, later topics under <other> (metrics.MAX_TOPIC_LABELS)",
    "metrics_lines": "2,000 topic labels x 5 families",
    "registry.": "10,000 robots; the 1,000 seen longest ago forgotten when full",
    "db_kib": "10,000 robot rows and the sessions' rows (session_expiry_s)",
    "recordings_kib": "recording.max_total_bytes (32 MiB here)",
    "core.keyframes.": "4,096 video topics (keyframes.MAX_VIDEO_TOPICS)",
    "core.sessions._offline._cache": "16,384 topics, then cleared (subscriptions)",
    "core.sessions.": "64 sessions per identity set; offline ones expire (session_expiry_s)",
    "metrics.session_drops": "2,000 (session, topic) labels (metrics.MAX_TOPIC_LABELS)",
    "sum(peer.outbound.": "per connection: outbound_queue_bytes and latched_bytes; freed "
                          "with it",
}


def cap_of(key: str) -> str | None:
    """The bound of series *key*, if :data:`CAPS` knows it."""
    return next((cap for prefix, cap in CAPS.items() if key.startswith(prefix)), None)


def _fit(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of *ys* over *xs* (0 for fewer than 3 points)."""
    if len(xs) < 3 or len(set(xs)) < 2:
        return 0.0
    return statistics.linear_regression(xs, ys).slope


def analyse(rows: list[dict[str, Any]], warmup_s: float) -> dict[str, dict[str, Any]]:
    """Per series: value after warm-up and at the end, slope per hour (after warm-up and
    over the last third), verdict."""
    after = [r for r in rows if r["t_s"] >= warmup_s] or rows
    half = after[len(after) * 2 // 3:]
    keys = sorted({k for r in rows for k in r if k != "t_s"})
    out: dict[str, dict[str, Any]] = {}
    for key in keys:
        if not all(key in r for r in after):
            continue
        ys = [float(r[key]) for r in after]
        slope = _fit([r["t_s"] for r in after], ys) * 3600
        late = _fit([r["t_s"] for r in half], [float(r[key]) for r in half]) * 3600
        span = max(ys) - min(ys)
        # Noise floor: 2 MiB of RSS, 1 % and 2 for counts; a slope under it over an hour
        # of the run's length is not growth.
        floor = 2048 if key.endswith("rss_kib") else max(2.0, 0.01 * max(abs(y) for y in ys))
        hours = (after[-1]["t_s"] - after[0]["t_s"]) / 3600 or 1.0
        if slope * hours <= floor or span <= floor:
            verdict = "flat"
        elif late * hours / 3 <= floor:
            verdict = "plateau"
        else:
            verdict = "GROWS" if cap_of(key) is None else "to cap"
        out[key] = {"start": ys[0], "end": ys[-1], "per_hour": slope, "late_per_hour": late,
                    "verdict": verdict, "cap": cap_of(key)}
    return out


def rereport(path: Path, warmup_s: float) -> None:
    """Analyse a report saved with ``--save`` again (``--reanalyse PATH``)."""
    saved = json.loads(path.read_text())
    args = argparse.Namespace(**{k: _number(v) for k, v in saved["args"].items()})
    args.json = False
    report(saved["rows"], analyse(saved["rows"], warmup_s), saved["tracemalloc"],
           saved["churn"], args)


def _number(text: str) -> Any:
    for kind in (int, float):
        with contextlib.suppress(ValueError):
            return kind(text)
    return {"True": True, "False": False, "None": None}.get(text, text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=5.0)
    parser.add_argument("--sample-s", type=float, default=10.0)
    parser.add_argument("--warmup-s", type=float, default=60.0)
    parser.add_argument("--robots", type=int, default=6)
    parser.add_argument("--viewers", type=int, default=4)
    parser.add_argument("--foxglove", type=int, default=2)
    parser.add_argument("--junk", type=int, default=2)
    parser.add_argument("--map-kib", type=int, default=256,
                        help="each robot name's latched map (fills the 64 MiB store in "
                             "~10 min)")
    parser.add_argument("--session-expiry-s", type=float, default=60.0,
                        help="sessions kept for resume (the default config: 3600)")
    parser.add_argument("--no-record", action="store_true", help="recording off")
    parser.add_argument("--mmap-threshold-kib", type=int, default=0,
                        help="set glibc's M_MMAP_THRESHOLD in the relay (fixed, not "
                             "adjusted): is RSS growth the allocator's?")
    parser.add_argument("--tracemalloc", action="store_true")
    parser.add_argument("--snapshot-s", type=float, default=0.0,
                        help="with --tracemalloc: when the first snapshot is taken "
                             "(default: at the end of warm-up)")
    parser.add_argument("--server-cpu", type=int, default=0)
    parser.add_argument("--client-cpu", type=int, default=1)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--save", type=Path, help="also write the JSON report to this file")
    parser.add_argument("--reanalyse", type=Path,
                        help="only analyse a report saved with --save again")
    args = parser.parse_args()
    if args.reanalyse is not None:
        rereport(args.reanalyse, args.warmup_s)
        return
    if not 1 <= args.robots <= 200:
        parser.error("--robots: 1 to 200 (one loopback address each)")
    rows, growth, counts = soak(args)
    result = analyse(rows, args.warmup_s)
    if args.save is not None:
        args.save.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                         "rows": rows, "series": result, "churn": counts,
                                         "tracemalloc": growth}, indent=1) + "\n")
    report(rows, result, growth, counts, args)


def soak(args: argparse.Namespace) -> tuple[list[dict[str, Any]], list[str], dict[str, int]]:
    rows: list[dict[str, Any]] = []
    growth: list[str] = []
    with tempfile.TemporaryDirectory() as directory:
        ports, samples, requests = mp.Queue(), mp.Queue(), mp.Queue()
        server = mp.Process(target=run_server, args=(args.server_cpu, directory, args, ports,
                                                     samples, requests), daemon=True)
        server.start()
        stop, results = mp.Event(), mp.Queue()
        try:
            port = ports.get(timeout=60)
            assert server.pid is not None
            churn = mp.Process(target=run_churn, args=(args.client_cpu, port, args, stop,
                                                       results))
            churn.start()
            started = time.monotonic()
            snapshot_taken = False
            while (t := time.monotonic() - started) < args.minutes * 60:
                if not snapshot_taken and t >= (args.snapshot_s or args.warmup_s):
                    requests.put("snapshot")
                    snapshot_taken = True
                else:
                    requests.put("sizes")
                row = {"t_s": round(t, 1), **_proc(server.pid), **_metrics(port),
                       **_disk(Path(directory)), **samples.get(timeout=60)}
                rows.append(row)
                print(_line(row), file=sys.stderr, flush=True)
                time.sleep(max(0.0, args.sample_s - (time.monotonic() - started - t)))
            stop.set()
            counts = results.get(timeout=60)
            churn.join(timeout=30)
            if args.tracemalloc and snapshot_taken:
                requests.put("growth")
                growth = samples.get(timeout=120)
        finally:
            stop.set()
            server.terminate()
            server.join()
    return rows, growth, counts


SHOWN = ("rss_kib", "fds", "threads", "tasks", "loop_timers", "gc_objects",
         "connections_open", "core.peers", "metrics_lines", "db_kib")


def _line(row: dict[str, Any]) -> str:
    return " ".join(f"{k}={row.get(k)}" for k in ("t_s", *SHOWN))


def report(rows: list[dict[str, Any]], result: dict[str, dict[str, Any]], growth: list[str],
           counts: dict[str, int], args: argparse.Namespace) -> None:
    if args.json:
        json.dump({"rows": rows, "series": result, "churn": counts, "tracemalloc": growth},
                  sys.stdout, indent=2)
        print()
        return
    print(f"relay soak: {args.minutes:g} min, {args.robots} robots, {args.viewers} viewers, "
          f"{args.foxglove} Foxglove clients, {args.junk} pests, session expiry "
          f"{args.session_expiry_s:g} s, recording {'off' if args.no_record else 'on'}")
    print("churn: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    print(" ".join(f"{k:>12}" for k in ("t_s", *SHOWN)))
    for row in rows:
        print(" ".join(f"{row.get(k, '-'):>12}" for k in ("t_s", *SHOWN)))
    print(f"\nafter {args.warmup_s:g} s of warm-up: start -> end, growth per hour "
          "(after warm-up; last third), verdict")
    for key, r in result.items():
        if r["verdict"] != "flat" or key in SHOWN:
            cap = f"  [{r['cap']}]" if r["verdict"] == "to cap" else ""
            print(f"  {key:<40} {r['start']:>10.0f} -> {r['end']:>10.0f}  "
                  f"{r['per_hour']:>+11.0f}/h {r['late_per_hour']:>+11.0f}/h  "
                  f"{r['verdict']}{cap}")
    growing = [k for k, r in result.items() if r["verdict"] == "GROWS"]
    verdict = "GROWS: " + ", ".join(growing) if growing else "nothing grows without a bound"
    print(f"verdict: {verdict} (series not listed: flat; 'to cap': still growing toward the "
          "bound shown)")
    for line in growth:
        print("  tracemalloc", line)


if __name__ == "__main__":
    main()
