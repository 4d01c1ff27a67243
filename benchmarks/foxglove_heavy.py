"""What a Foxglove viewer of heavy topics costs every other connection of the relay.

Usage::

    .venv/bin/python benchmarks/foxglove_heavy.py [--seconds 10] [--path-poses 2000]
        [--markers 300] [--server-cpu 0] [--client-cpu 1] [--json]

The relay (:class:`fleetctl.server.app.RelayServer`) runs in its own process pinned to one
core, with a task on its event loop that sleeps 5 ms again and again and records how late
it wakes (the loop's lag). On the other core, one process holds:

- a robot sending a ``nav_msgs/msg/Path`` of ``--path-poses`` poses at 5 Hz, a
  ``visualization_msgs/msg/MarkerArray`` of ``--markers`` line strips of 50 points at
  2 Hz (the robot graph's planner and obstacle layers, docs/benchmarks.md) and a small
  ``geometry_msgs/msg/PoseStamped`` at 20 Hz stamped with its send time;
- a fleetctl consumer of the pose (the latency probe: receive - send, one host clock);
- in the second phase, a Foxglove viewer (``foxglove.websocket.v1``, a Bearer token on
  the upgrade) subscribed to the Path and the MarkerArray: the relay converts them to CDR.

Two phases of ``--seconds`` each, without then with the viewer: the probe's p50/p99/max,
the loop's lag p50/p99/max, the CPU of the relay's loop thread and of its other threads
(the conversion thread: ``/proc/PID/task``), what the viewer received and the frames the
relay superseded for it. Lag and latency follow the host's load; the loop thread's CPU
does not, and says where the conversion ran.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hashlib
import json
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROBOT_TOKEN = "foxglove-heavy-robot"
VIEWER_TOKEN = "foxglove-heavy-viewer"
LAG_TICK_S = 0.005


def _pin(cpu: int) -> None:
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setaffinity(0, {cpu})


def _sha(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def run_relay(cpu: int, ports: Any, stop: Any, lags: Any) -> None:
    """The relay, and a probe of its loop's lag: ``(wall time, lateness s)`` pairs."""
    _pin(cpu)
    from fleetctl.server.app import RelayServer
    from fleetctl.server.authmap import parse_auth_map
    from fleetctl.server.config import ServerConfig

    auth = parse_auth_map({"identities": [
        {"name": "robot", "token_sha256": _sha(ROBOT_TOKEN),
         "rules": [{"topic": "/r/.*", "op": "both"}]},
        {"name": "viewer", "token_sha256": _sha(VIEWER_TOKEN),
         "rules": [{"topic": "/r/.*", "op": "receive"}]}]}, Path("bench-auth.yaml"))
    db = Path(tempfile.mkdtemp()) / "fleet.db"
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=Path("-"),
                          database=db)

    async def lag_probe(out: list[tuple[float, float]]) -> None:
        while True:
            t0 = time.monotonic()
            await asyncio.sleep(LAG_TICK_S)
            out.append((time.time(), time.monotonic() - t0 - LAG_TICK_S))

    async def main() -> None:
        out: list[tuple[float, float]] = []
        async with RelayServer(config, auth) as srv:
            probe = asyncio.create_task(lag_probe(out))
            ports.put(srv.port)
            while not stop.is_set():
                await asyncio.sleep(0.1)
            probe.cancel()
        lags.put(out)

    asyncio.run(main())


def heavy_frames(poses: int, markers: int) -> dict[str, bytes]:
    """The Path and MarkerArray frames the robot sends, built with the wire's typestore."""
    from fleetctl.wire.codec import default_codec

    codec = default_codec()
    t = codec.registry.typestore.types

    def header(frame: str = "map") -> Any:
        return t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id=frame)

    def point(x: float, y: float) -> Any:
        return t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0)

    quat = t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    path = t["nav_msgs/msg/Path"](header=header(), poses=[
        t["geometry_msgs/msg/PoseStamped"](
            header=header(), pose=t["geometry_msgs/msg/Pose"](position=point(0.05 * k, 0.0),
                                                              orientation=quat))
        for k in range(poses)])
    color = t["std_msgs/msg/ColorRGBA"](r=1.0, g=0.0, b=0.0, a=1.0)
    marker_cls = t["visualization_msgs/msg/Marker"]
    array = t["visualization_msgs/msg/MarkerArray"](markers=[
        marker_cls(
            header=header(), ns="obstacles", id=k, type=marker_cls.LINE_STRIP,
            action=marker_cls.ADD,
            pose=t["geometry_msgs/msg/Pose"](position=point(0.0, 0.0), orientation=quat),
            scale=t["geometry_msgs/msg/Vector3"](x=0.05, y=0.0, z=0.0), color=color,
            lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
            frame_locked=False, points=[point(0.1 * j, 0.1 * k) for j in range(50)],
            colors=[], texture_resource="",
            texture=t["sensor_msgs/msg/CompressedImage"](header=header(), format="",
                                                         data=_empty_u8()),
            uv_coordinates=[], text="", mesh_resource="",
            mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=_empty_u8()),
            mesh_use_embedded_materials=False)
        for k in range(markers)])
    return {"/r/plan": codec.encode(path, "nav_msgs/msg/Path", "/r/plan"),
            "/r/markers": codec.encode(array, "visualization_msgs/msg/MarkerArray",
                                       "/r/markers")}


def _empty_u8() -> Any:
    import numpy as np

    return np.zeros(0, dtype=np.uint8)


def pose_frame(stamp_ns: int) -> bytes:
    from fleetctl.wire.codec import default_codec

    codec = default_codec()
    t = codec.registry.typestore.types
    msg = t["geometry_msgs/msg/PoseStamped"](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=0,
                                                                                nanosec=0),
                                        frame_id="map"),
        pose=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
    return codec.encode(msg, "geometry_msgs/msg/PoseStamped", "/r/pose",
                        publish_time_ns=stamp_ns)


async def robot(port: int, frames: dict[str, bytes], stop: asyncio.Event) -> None:
    """Path at 5 Hz, MarkerArray at 2 Hz, the stamped pose at 20 Hz."""
    from websockets.asyncio.client import connect

    async with connect(f"ws://127.0.0.1:{port}/", max_size=None, compression=None,
                       additional_headers={"Authorization": f"Bearer {ROBOT_TOKEN}"}) as ws:
        start = time.monotonic()
        ticks = 0
        while not stop.is_set():
            # 20 ticks a second: the pose every tick, the Path every 4th, markers every 10th.
            if ticks % 4 == 0:
                await ws.send(frames["/r/plan"])
            if ticks % 10 == 0:
                await ws.send(frames["/r/markers"])
            await ws.send(pose_frame(time.time_ns()))
            ticks += 1
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), max(0.0, start + ticks / 20 - time.monotonic()))


async def probe(port: int, latencies_ms: list[float], ready: asyncio.Event) -> None:
    from websockets.asyncio.client import connect

    from fleetctl.wire.control import encode_subscription
    from fleetctl.wire.metadata import read_metadata

    async with connect(f"ws://127.0.0.1:{port}/", max_size=None, compression=None,
                       additional_headers={"Authorization": f"Bearer {ROBOT_TOKEN}"}) as ws:
        await ws.send(encode_subscription("/r/pose"))
        ready.set()
        async for message in ws:
            if isinstance(message, bytes):
                meta = read_metadata(message)
                if meta.topic == "/r/pose" and meta.publish_time_ns:
                    latencies_ms.append((time.time_ns() - meta.publish_time_ns) / 1e6)


async def viewer(port: int, received: dict[str, int]) -> None:
    """A Foxglove viewer subscribed to every channel but the pose."""
    from websockets.asyncio.client import connect

    subscribed: dict[int, str] = {}
    async with connect(f"ws://127.0.0.1:{port}/", max_size=None, compression=None,
                       subprotocols=["foxglove.websocket.v1"],  # type: ignore[list-item]
                       additional_headers={"Authorization": f"Bearer {VIEWER_TOKEN}"}) as ws:
        async for message in ws:
            if isinstance(message, bytes):
                topic = subscribed.get(int.from_bytes(message[1:5], "little"), "?")
                received[topic] = received.get(topic, 0) + 1
                continue
            data = json.loads(message)
            if data.get("op") == "advertise":
                subs = []
                for channel in data["channels"]:
                    if channel["topic"] != "/r/pose":
                        subscribed[len(subscribed) + 1] = channel["topic"]
                        subs.append({"id": len(subscribed), "channelId": channel["id"]})
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))


def _cpu_s(pid: int) -> tuple[float, float]:
    """CPU seconds of the relay's loop thread (its main thread) and of its other threads
    (the conversion thread among them): robust to a busy host, unlike the lag."""
    loop = other = 0.0
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
            cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
            if task.name == str(pid):
                loop += cpu
            else:
                other += cpu
    return loop, other


def _metric(port: int, prefix: str) -> float:
    import urllib.request

    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as answer:
        text = answer.read().decode()
    return sum(float(line.rpartition(" ")[2]) for line in text.splitlines()
               if line.startswith(prefix))


def _stats(values: list[float]) -> dict[str, float]:
    if not values:
        return {"n": 0}
    ordered = sorted(values)
    return {"n": len(ordered), "p50": round(statistics.median(ordered), 2),
            "p99": round(ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))], 2),
            "max": round(ordered[-1], 2)}


async def phase(port: int, pid: int, frames: dict[str, bytes], seconds: float,
                with_viewer: bool) -> dict[str, Any]:
    stop = asyncio.Event()
    latencies: list[float] = []
    received: dict[str, int] = {}
    ready = asyncio.Event()
    tasks = [asyncio.create_task(probe(port, latencies, ready))]
    await ready.wait()
    if with_viewer:
        tasks.append(asyncio.create_task(viewer(port, received)))
    sender = asyncio.create_task(robot(port, frames, stop))
    await asyncio.sleep(1.0)  # warm-up: subscriptions settle, the first frames convert
    latencies.clear()
    received.clear()
    superseded = _metric(port, "fleetctl_foxglove_superseded_total")
    cpu0, wall0, t0 = _cpu_s(pid), time.time(), time.monotonic()
    await asyncio.sleep(seconds)
    elapsed = time.monotonic() - t0
    cpu1, wall1 = _cpu_s(pid), time.time()
    superseded = _metric(port, "fleetctl_foxglove_superseded_total") - superseded
    stop.set()
    await sender
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    return {"viewer": with_viewer, "window": (wall0, wall1),
            "probe_ms": _stats(latencies),
            "relay_loop_cpu_pct": round(100 * (cpu1[0] - cpu0[0]) / elapsed, 1),
            "relay_other_cpu_pct": round(100 * (cpu1[1] - cpu0[1]) / elapsed, 1),
            "viewer_per_s": {k: round(v / elapsed, 1) for k, v in sorted(received.items())},
            "superseded": superseded}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="each phase (10)")
    parser.add_argument("--path-poses", type=int, default=2000, help="poses per Path (2000)")
    parser.add_argument("--markers", type=int, default=300,
                        help="line strips of 50 points per MarkerArray (300)")
    parser.add_argument("--server-cpu", type=int, default=0)
    parser.add_argument("--client-cpu", type=int, default=1)
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    args = parser.parse_args()

    ctx = mp.get_context("spawn")
    ports, lags, stop = ctx.Queue(), ctx.Queue(), ctx.Event()
    relay = ctx.Process(target=run_relay, args=(args.server_cpu, ports, stop, lags))
    relay.start()
    _pin(args.client_cpu)
    port = ports.get(timeout=30)
    frames = heavy_frames(args.path_poses, args.markers)

    async def run() -> list[dict[str, Any]]:
        return [await phase(port, relay.pid or 0, frames, args.seconds, False),
                await phase(port, relay.pid or 0, frames, args.seconds, True)]

    rows = asyncio.run(run())
    stop.set()
    lag = lags.get(timeout=30)
    relay.join(30)
    for row in rows:
        start, end = row.pop("window")
        row["loop_lag_ms"] = _stats([late * 1e3 for at, late in lag if start <= at <= end])
    out = {"frame_bytes": {k: len(v) for k, v in frames.items()}, "phases": rows}
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"frames: {out['frame_bytes']}; {args.seconds:.0f} s per phase; relay on cpu "
          f"{args.server_cpu}, clients on cpu {args.client_cpu}")
    for row in rows:
        p, lg = row["probe_ms"], row["loop_lag_ms"]
        print(f"{'with' if row['viewer'] else 'without':>7} viewer: pose probe p50 "
              f"{p.get('p50')} p99 {p.get('p99')} max {p.get('max')} ms (n {p['n']}); "
              f"loop lag p50 {lg.get('p50')} p99 {lg.get('p99')} max {lg.get('max')} ms; "
              f"relay CPU: loop thread {row['relay_loop_cpu_pct']} %, other threads "
              f"{row['relay_other_cpu_pct']} %; viewer got {row['viewer_per_s']} /s; "
              f"superseded {row['superseded']:.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
