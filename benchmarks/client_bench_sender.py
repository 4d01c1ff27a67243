"""Benchmark helper: one sending robot (RobotLink, Robofleet-like baseline, or plain ws).

Run by ``benchmarks/client_link.py`` (possibly inside a network namespace); prints one
JSON line with its own measurements. Scenarios:

- ``throughput``: N frames of SIZE bytes, offered at once as no_drop (the link sends as
  fast as its window allows) or, for ``--mode raw``, sent back to back on a plain
  websockets connection. Prints the wall-clock start in ns.
- ``priority``: a 1 KB topic at 50 Hz (priority 10) and, with ``--cloud``, a 64 KB topic
  at 6.7 Hz (priority 1), both droppable, for ``--seconds``.
- ``slow``: one droppable topic of ``--size`` bytes (``--payload``) every ``--period`` s
  for ``--seconds``, on a link slower than it (part (f)): what the link spends on messages
  it abandons, and with ``--count-dev`` the bytes the interface sent for them.
- ``speedup``: issue 19's load with the e2e load's real scan and pose, the link's view
  printed four times a second (part (g): the caller changes the shaping meanwhile).
- ``cpu``: a 10 Hz 1 MB ``sensor_msgs/msg/PointCloud2`` for ``--seconds``: per message CDR
  -> message (rosbags) -> FlatBuffer (codec) -> link, i.e. the ROS node's per-message path
  without rclpy's own receive. Prints CPU seconds and RSS.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import resource
import time
from pathlib import Path
from typing import Any

import numpy as np
from websockets.asyncio.client import connect

from fleetctl.client.config import parse_client_config
from fleetctl.client.linktuning import LinkTuning
from fleetctl.client.scheduler import SchedulerConfig
from fleetctl.client.slowdeflate import SlowDeflateSettings
from fleetctl.client.transport import RobotLink, scheduler_config_for
from fleetctl.e2e import payloads
from fleetctl.wire import samples
from fleetctl.wire.codec import default_codec

ROBOT_TOKEN = "bench-robot-token"


def string_frame(topic: str, size: int, seq: int, *, no_drop: bool) -> bytes:
    codec = default_codec()
    cls = codec.registry.get("std_msgs/msg/String").cls
    return codec.encode(cls("x" * size), "std_msgs/msg/String", topic, no_drop=no_drop,
                        seq=seq, publish_time_ns=time.time_ns())


def make_link(url: str, mode: str, fragment_bytes: int, batch_bytes: int = 1024 * 1024,
              write_limit: int = 1024 * 1024, tuning: LinkTuning | None = None) -> RobotLink:
    config = parse_client_config({
        "server_url": url, "robot_name": "bench",
        "limits": {"max_fragment_bytes": fragment_bytes}})
    config = dataclasses.replace(config, token=ROBOT_TOKEN)
    sched = scheduler_config_for(config)
    if mode == "baseline":  # Robofleet: n_T = 1, whole messages
        sched = dataclasses.replace(sched, fixed_window_messages=1, fragments=False)
    tuning = dataclasses.replace(tuning or LinkTuning(), send_batch_bytes=batch_bytes,
                                 write_limit_bytes=write_limit)
    return RobotLink(config, on_frame=lambda f: None, scheduler_config=sched, tuning=tuning)


async def wait_connected(link: RobotLink) -> None:
    deadline = time.monotonic() + 10
    while not link.stats()["identities"]:
        if time.monotonic() > deadline:
            raise SystemExit(f"link did not connect: {link.stats()['last_close']}")
        await asyncio.sleep(0.01)


async def throughput(args: argparse.Namespace) -> dict[str, Any]:
    frame = string_frame("/bench/bulk", args.size, 1, no_drop=True)
    if args.mode == "raw":
        async with connect(args.url, additional_headers={"Authorization": f"Bearer {ROBOT_TOKEN}"},
                           compression=None, proxy=None, max_size=None) as ws:
            start, cpu0 = time.perf_counter(), time.process_time()
            for _ in range(args.frames):
                await ws.send(frame)
            await (await ws.ping())  # the pong: the relay has read everything before it
            return {"seconds": time.perf_counter() - start, "bytes": args.frames * len(frame),
                    "cpu_s": time.process_time() - cpu0}
    link = make_link(args.url, args.mode, args.fragment_bytes, args.batch_bytes,
                     args.write_limit)
    task = asyncio.create_task(link.run())
    await wait_connected(link)
    start, cpu0 = time.perf_counter(), time.process_time()
    offered = 0
    deadline = time.monotonic() + 300
    sched = link.scheduler
    # A producer that keeps 512 frames queued (the no_drop queue is bounded; offering
    # everything at once would overflow it and count refused frames as sent).
    while offered < args.frames or sched.in_flight_bytes or sched.has_sendable():
        for _ in range(min(512 - sched.no_drop_queued, args.frames - offered)):
            link.offer("/bench/bulk", frame, priority=1.0, no_drop=True)
            offered += 1
        if time.monotonic() > deadline:
            raise SystemExit(f"not all acknowledged: {link.stats()['topics']}")
        await asyncio.sleep(0.0005)  # producer period; the link runs meanwhile
    seconds, cpu_s = time.perf_counter() - start, time.process_time() - cpu0
    stats = link.stats()
    await link.stop()
    await task
    acked = stats["topics"]["/bench/bulk"]["acked"]
    if acked != args.frames or stats["no_drop_overflow"]:
        raise SystemExit(f"acked {acked} of {args.frames}, overflow {stats['no_drop_overflow']}")
    return {"seconds": seconds, "bytes": acked * len(frame), "cpu_s": cpu_s,
            "window_bytes": stats["window_bytes"], "min_rtt_ms": stats["min_rtt_ms"]}


async def drained(link: RobotLink, timeout_s: float = 5.0) -> None:
    """Wait until everything offered was sent and acknowledged (or *timeout_s*)."""
    deadline = time.monotonic() + timeout_s
    sched = link.scheduler
    while (sched.in_flight_bytes or sched.has_sendable()) and time.monotonic() < deadline:
        await asyncio.sleep(0.005)  # poll with a deadline


async def periodic(period_s: float, stop_at: float, action: Any) -> None:
    """Call *action* every *period_s* until *stop_at* (a source, like a ROS timer)."""
    nxt = time.monotonic()
    while nxt < stop_at:
        action()
        nxt += period_s
        await asyncio.sleep(max(0.0, nxt - time.monotonic()))


async def priority(args: argparse.Namespace) -> dict[str, Any]:
    link = make_link(args.url, args.mode, args.fragment_bytes)
    task = asyncio.create_task(link.run())
    await wait_connected(link)
    seqs = {"/bench/urgent": 0, "/bench/cloud": 0, "/bench/events": 0}
    prefix = "/bench/warmup_"  # not subscribed by the consumer: the link learns the rate

    def offer(topic: str, size: int, prio: float, no_drop: bool = False) -> None:
        topic = topic.replace("/bench/", prefix)
        seqs[topic] = seqs.get(topic, 0) + 1
        link.offer(topic, string_frame(topic, size, seqs[topic], no_drop=no_drop),
                   priority=prio, no_drop=no_drop)

    warm_until = time.monotonic() + args.warmup
    warm = [periodic(0.02, warm_until, lambda: offer("/bench/urgent", 1000, 10.0))]
    if args.cloud:
        warm.append(periodic(0.15, warm_until, lambda: offer("/bench/cloud", 64_000, 1.0)))
    await asyncio.gather(*warm)
    prefix = "/bench/"
    stop_at = time.monotonic() + args.seconds
    windows: list[tuple[int, int, float]] = []

    def sample() -> None:
        st = link.scheduler
        windows.append((st.window_bytes(), st.fragment_bytes(), st.in_flight_bytes))

    jobs = [periodic(0.02, stop_at, lambda: offer("/bench/urgent", 1000, 10.0)),
            periodic(0.5, stop_at, sample)]
    if args.cloud:
        jobs.append(periodic(0.15, stop_at, lambda: offer("/bench/cloud", 64_000, 1.0)))
    if args.events:
        jobs.append(periodic(0.1, stop_at, lambda: offer("/bench/events", 100, 1.0, True)))
    await asyncio.gather(*jobs)
    await drained(link, 10.0 if args.events else 5.0)
    stats = link.stats()
    await link.stop()
    await task
    return {"sent": seqs, "topics": stats["topics"], "window_bytes": stats["window_bytes"],
            "min_rtt_ms": stats["min_rtt_ms"], "fragment_bytes": stats["fragment_bytes"],
            "delivery_rate_Bps": stats["delivery_rate_Bps"], "windows": windows,
            "reconnects": stats["reconnects"], "link_timeouts": stats["link_timeouts"],
            "uplink_deflate": stats["uplink_deflate"]}


def payload_messages(kind: str, size: int, count: int = 8) -> tuple[str, list[Any]]:
    """*count* messages of about *size* bytes and their type: ``string`` (one letter
    repeated: deflate takes it to ~1 %), ``image`` (a CompressedImage of random bytes, as
    incompressible as a JPEG or a video frame) or ``cloud`` (a PointCloud2 of normally
    distributed float32 points: deflate keeps ~90 %)."""
    registry = default_codec().registry
    if kind == "string":
        cls = registry.get("std_msgs/msg/String").cls
        return "std_msgs/msg/String", [cls("x" * size)] * count
    if kind == "image":
        return "sensor_msgs/msg/CompressedImage", [
            samples.compressed_image(registry, size, seed=i) for i in range(count)]
    columns = max(1, size // (16 * 16))
    return "sensor_msgs/msg/PointCloud2", [
        samples.point_cloud(registry, 16, columns, seed=i) for i in range(count)]


def tx_bytes(dev: str) -> int:
    """Bytes the interface *dev* of this network namespace has sent (IP headers and all)."""
    return int(Path(f"/sys/class/net/{dev}/statistics/tx_bytes").read_text())


async def slow_link(args: argparse.Namespace) -> dict[str, Any]:
    tuning = None if args.slow_deflate else LinkTuning(
        slow_deflate=SlowDeflateSettings(on_below_Bps=0.0))
    link = make_link(args.url, "link", args.fragment_bytes, tuning=tuning)
    task = asyncio.create_task(link.run())
    await wait_connected(link)
    seqs: dict[str, int] = {}
    type_name, messages = payload_messages(args.payload, args.size)
    codec = default_codec()
    frame_bytes: list[int] = []

    def offer(topic: str) -> None:
        seqs[topic] = seqs.get(topic, 0) + 1
        frame = codec.encode(messages[seqs[topic] % len(messages)], type_name, topic,
                             seq=seqs[topic], publish_time_ns=time.time_ns())
        frame_bytes.append(len(frame))
        link.offer(topic, frame, priority=1.0, no_drop=False)

    # The same flow on a topic the consumer does not take first: the link learns its rate.
    await periodic(args.period, time.monotonic() + args.warmup,
                   lambda: offer("/bench/warmup_cloud"))
    await drained(link)
    wire_before = tx_bytes(args.count_dev) if args.count_dev else 0
    cpu_before = time.process_time()
    await periodic(args.period, time.monotonic() + args.seconds,
                   lambda: offer("/bench/cloud"))
    await drained(link)
    cpu_s = time.process_time() - cpu_before
    wire = tx_bytes(args.count_dev) - wire_before if args.count_dev else None
    stats = link.stats()
    await link.stop()
    await task
    return {"sent": seqs, "topic": stats["topics"]["/bench/cloud"], "wire_bytes": wire,
            "frame_bytes": frame_bytes[-1], "cpu_s": cpu_s,
            "uplink_deflate": stats["uplink_deflate"]}


# Issue 19's topics as the e2e load publishes them: (topic, period s, type, size asked of
# fleetctl.e2e.payloads, priority, the string frame's text length); frames of 256 and
# 5,968 bytes, the string frames 200 and 5,928.
PEER_LOAD = (("/bench/pose", 0.05, "geometry_msgs/msg/PoseStamped", 256, 2.0, 86),
             ("/bench/scan", 0.1, "sensor_msgs/msg/LaserScan", 5760, 1.0, 5814))


class PeerFrames:
    """The frames of :data:`PEER_LOAD`, each stamped when made: the e2e load's messages
    (``real``: a scan deflates to ~0.58 of its size, a pose to ~0.15), or (``string``,
    the figures before 2026-12-07) std_msgs/String frames of about their sizes holding
    one repeated letter, which deflates to ~2 %: so far below the slow-link rule's trusted
    share that the robot deflates every message, with zlib, on any link."""

    def __init__(self, payload: str) -> None:
        self.codec = default_codec()
        self.real = payload == "real"
        self.seqs: dict[str, int] = {}
        self.topics = {topic: (type_name, size, text)
                       for topic, _, type_name, size, _, text in PEER_LOAD}

    def make(self, topic: str) -> bytes:
        """The next frame of *topic* (a topic of :data:`PEER_LOAD`, or one with
        ``_warm`` appended)."""
        type_name, size, text = self.topics[topic.removesuffix("_warm")]
        seq = self.seqs[topic] = self.seqs.get(topic, 0) + 1
        if not self.real:
            return string_frame(topic, text, seq, no_drop=False)
        msg = payloads.build(self.codec.registry.typestore, type_name, size, seq,
                             time.time_ns())
        # Stamped after the message is built (the scan's ray casting takes ~0.1 ms, which
        # a robot's sensor driver spends before it publishes), before it is encoded (the
        # robot's own work, as in the string frames).
        return self.codec.encode(msg, type_name, topic, seq=seq,
                                 publish_time_ns=time.time_ns())


async def peer_load(args: argparse.Namespace) -> dict[str, Any]:
    """Issue 19's load (:class:`PeerFrames`: the pose at 20 Hz, the 720-beam scan at 10
    Hz), droppable, each stamped when made; through RobotLink, or (``--mode raw``)
    written on a plain websockets connection as soon as it is made."""
    frames = PeerFrames(args.payload)
    topics = tuple((topic, period, 0, prio) for topic, period, _, _, prio, _ in PEER_LOAD)
    if args.mode == "raw":
        async with connect(args.url, additional_headers={"Authorization": f"Bearer {ROBOT_TOKEN}"},
                           compression=None, proxy=None, max_size=None) as ws:
            pending: set[asyncio.Task[None]] = set()

            def send(topic: str, _size: int, _prio: float) -> None:
                task = asyncio.ensure_future(ws.send(frames.make(topic)))
                pending.add(task)
                task.add_done_callback(pending.discard)

            await _run_topics(topics, args, send)
            await asyncio.gather(*pending)
            await (await ws.ping())
            return {"sent": frames.seqs}
    link = make_link(args.url, args.mode, args.fragment_bytes)
    task = asyncio.create_task(link.run())
    await wait_connected(link)

    def offer(topic: str, _size: int, prio: float) -> None:
        link.offer(topic, frames.make(topic), priority=prio, no_drop=False)

    await _run_topics(topics, args, offer)
    await drained(link)
    stats = link.stats()
    await link.stop()
    await task
    return {"sent": frames.seqs, "window_bytes": stats["window_bytes"],
            "fragment_bytes": stats["fragment_bytes"], "min_rtt_ms": stats["min_rtt_ms"],
            "delivery_rate_Bps": stats["delivery_rate_Bps"],
            "deflate_all": stats["uplink_deflate"]["all_messages"],
            "wire_share": stats["uplink_deflate"]["wire_share"]}


REPORT_EVERY_S = 0.25


async def speedup(args: argparse.Namespace) -> dict[str, Any]:
    """Issue 19's load with the e2e load's messages (:class:`PeerFrames`), printing the
    link's view every :data:`REPORT_EVERY_S` as a JSON line (``{"t": ..., "deflate_all":
    ...}``), while the caller changes the link's shaping from outside (part (g))."""
    frames = PeerFrames("real")
    link = make_link(args.url, "link", args.fragment_bytes)
    task = asyncio.create_task(link.run())
    await wait_connected(link)
    start = time.monotonic()
    stop_at = start + args.seconds

    async def report() -> None:
        while time.monotonic() < stop_at:
            await asyncio.sleep(REPORT_EVERY_S)
            st = link.stats()
            print(json.dumps({
                "t": round(time.monotonic() - start, 2),
                "deflate_all": st["uplink_deflate"]["all_messages"],
                "wire_share": st["uplink_deflate"]["wire_share"],
                "link_rate_Bps": st["link_rate_Bps"], "fragment_bytes": st["fragment_bytes"],
                "window_bytes": st["window_bytes"]}), flush=True)

    await asyncio.gather(*(
        periodic(period, stop_at, lambda t=topic, p=prio: link.offer(
            t, frames.make(t), priority=p, no_drop=False))
        for topic, period, _, _, prio, _ in PEER_LOAD), report())
    stats = link.stats()
    await link.stop()
    await task
    return {"sent": frames.seqs, "switches": stats["uplink_deflate"]["switches"]}


async def _run_topics(topics: tuple[tuple[str, float, int, float], ...],
                      args: argparse.Namespace, action: Any) -> None:
    """Run every topic's timer for ``--warmup`` seconds on unmeasured ``_warm`` topics,
    then for ``--seconds``."""
    for suffix, seconds in (("_warm", args.warmup), ("", args.seconds)):
        stop_at = time.monotonic() + seconds
        await asyncio.gather(*(
            periodic(period, stop_at,
                     lambda t=topic + suffix, n=size, p=prio: action(t, n, p))
            for topic, period, size, prio in topics))


def pointcloud_cdr(size_bytes: int) -> tuple[bytes, Any]:
    codec = default_codec()
    store = codec.registry.typestore
    types = store.types
    header = types["std_msgs/msg/Header"](types["builtin_interfaces/msg/Time"](1, 2), "lidar")
    field_cls = types["sensor_msgs/msg/PointField"]
    fields = [field_cls(n, 4 * i, 7, 1) for i, n in enumerate("xyz")] + [
        field_cls("intensity", 12, 7, 1)]
    points = size_bytes // 16
    data = np.random.default_rng(0).integers(0, 255, points * 16, dtype=np.uint8)
    cloud = types["sensor_msgs/msg/PointCloud2"](header, 1, points, fields, False, 16,
                                                 points * 16, data, True)
    return bytes(store.serialize_cdr(cloud, "sensor_msgs/msg/PointCloud2")), store


async def cpu(args: argparse.Namespace) -> dict[str, Any]:
    link = make_link(args.url, "link", args.fragment_bytes)
    task = asyncio.create_task(link.run())
    await wait_connected(link)
    cdr, store = pointcloud_cdr(1_000_000)
    codec = default_codec()
    seq = 0

    def publish() -> None:
        nonlocal seq
        seq += 1
        # As the client's node does (fleetctl.client.ros.bridge): CDR as a view, frame as
        # a view of the builder's buffer.
        msg = store.deserialize_cdr(memoryview(cdr), "sensor_msgs/msg/PointCloud2")
        frame = codec.encode_view(msg, "sensor_msgs/msg/PointCloud2", "/bench/points",
                                  seq=seq, publish_time_ns=time.time_ns())
        if link.admit("/bench/points"):
            link.offer("/bench/points", frame, priority=1.0, no_drop=False)

    await periodic(0.1, time.monotonic() + 1.0, publish)  # warm-up (caches, window)
    cpu0, wall0 = time.process_time(), time.monotonic()
    await periodic(0.1, time.monotonic() + args.seconds, publish)
    cpu_s, wall_s = time.process_time() - cpu0, time.monotonic() - wall0
    stats = link.stats()
    await link.stop()
    await task
    with open("/proc/self/status") as status:
        rss_kb = next(int(line.split()[1]) for line in status if line.startswith("VmRSS:"))
    return {"cpu_s": cpu_s, "wall_s": wall_s, "cpu_percent": 100 * cpu_s / wall_s,
            "rss_mb": rss_kb / 1024, "max_rss_mb": resource.getrusage(
                resource.RUSAGE_SELF).ru_maxrss / 1024, "frame_bytes": len(cdr),
            "sent": stats["topics"]["/bench/points"]["sent"], "offered": seq}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("scenario", choices=["throughput", "priority", "cpu", "peer", "slow",
                                             "speedup"])
    parser.add_argument("--url", required=True)
    parser.add_argument("--mode", choices=["link", "baseline", "raw"], default="link")
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--size", type=int, default=65536)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--period", type=float, default=0.2, help="slow: offer interval (s)")
    parser.add_argument("--payload", choices=["string", "image", "cloud", "real"],
                        default="string",
                        help="slow: what the large message holds (string, image, cloud); "
                             "peer: string or real (PeerFrames)")
    parser.add_argument("--count-dev", default="",
                        help="slow: the interface whose sent bytes are counted")
    parser.add_argument("--no-slow-deflate", dest="slow_deflate", action="store_false",
                        help="slow: never deflate fragments (the behaviour before it)")
    parser.add_argument("--cloud", action="store_true")
    parser.add_argument("--events", action="store_true", help="add a 10 Hz no_drop topic")
    parser.add_argument("--batch-bytes", type=int, default=1024 * 1024)
    parser.add_argument("--write-limit", type=int, default=1024 * 1024)
    parser.add_argument("--warmup", type=float, default=1.0,
                        help="seconds of the same flows on unmeasured topics first")
    parser.add_argument("--fragment-bytes", type=int, default=SchedulerConfig().max_fragment_bytes)
    args = parser.parse_args()
    run = {"throughput": throughput, "priority": priority, "cpu": cpu,
           "peer": peer_load, "slow": slow_link,
           "speedup": speedup}[args.scenario]
    print(json.dumps(asyncio.run(run(args))), flush=True)


if __name__ == "__main__":
    main()
