"""A realistic robot's ROS 2 graph through the real client and relay: CPU, RSS, drops.

Usage::

    .venv/bin/python benchmarks/robot_graph.py [--seconds 60] [--json out.json]
        [--image-rate-hz 30] [--rosout-per-s 1000] [--plan-hz 5] [--markers-hz 2]
        [--heavy-rate-limit-hz HZ] [--map-cells 4000] [--foxglove] [--keep DIR]

The demo and the tests use a handful of small topics. A nav2/perception robot's graph is
richer, and this puts one through ``fleetctl client`` (real rclpy node) and ``fleetctl
server`` (real relay) on this machine, with a plain WebSocket consumer subscribed to
everything the robot sends, and prints what it cost and what arrived. The graph, from one
rclpy publisher process (pre-serialized CDR, so the publishers cost little):

- ``/tf`` 100 Hz with 40 moving frames (the client's ``tf:`` republisher) and
  ``/tf_static`` from 3 TRANSIENT_LOCAL publishers (robot_state_publisher and two drivers);
- ``/points`` PointCloud2 ~300 KB at 10 Hz; ``/camera/image_raw`` Image 640x480 rgb8 at 30 Hz
  (sent raw, as a team that has not read about ``video:`` would) and its
  ``/camera/image_raw/compressed`` CompressedImage (~60 KB) at 30 Hz;
- ``/imu/data`` Imu at 200 Hz; ``/diagnostics`` DiagnosticArray at 1 Hz from 2 publishers;
  ``/rosout`` flooded (``--rosout-per-s``); ``/plan`` Path of 2,000 poses at 5 Hz;
  ``/markers`` MarkerArray of 300 line-strip markers of 50 points at 2 Hz;
- ``/map`` OccupancyGrid 4000x4000 (16 MB) TRANSIENT_LOCAL, published once before the
  client starts; a late viewer subscribes to it at the end and times its arrival;
- a deep namespace (``/rg/sensors/front/lidar/scan``), a ``~``-relative name
  (``~/state`` of node ``/rg/driver``: ``/rg/driver/state``), ``nav_msgs/msg/Goals`` (new
  in Jazzy, not in rosbags' store: the relay did not know it until fleetctl shipped its
  definition), ``/odom`` published
  BEST_EFFORT (sensor drivers' usual QoS) and coming and going every 5 s, and ``/battery``
  with two publishers of different types.

Figures: the client's and the relay's CPU (% of one core, from /proc/PID/stat over the
measured window) and RSS (VmRSS, peak of 1 s samples and end); per topic what the
publisher sent, what the client took and sent, what the consumer received; the relay's
``fleetctl_drops_total``; the client's WARNING/ERROR lines (deduplicated); the late map;
the latency (robot's take -> consumer, one clock) of the small topics; the link's window,
RTT and rates halfway (the client's SIGUSR1 stats line); with ``--foxglove`` what a
Foxglove viewer received. ``diagnostic_msgs`` (``ros-jazzy-diagnostic-msgs``) is needed
for ``/diagnostics``, which is left out without it. Figures: docs/benchmarks.md, "A
realistic robot graph".
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hashlib
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections import Counter
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
PY = sys.executable
ROBOT = "rg"
ROBOT_IP = "127.0.1.31"
CONSUMER_TOKEN = "robot-graph-consumer-token"
DOMAIN_ID = "86"  # a domain no test uses
TICKS = os.sysconf("SC_CLK_TCK")

# The graph's topics: local topic, type, nominal rate (None: once or irregular).
TOPICS: list[tuple[str, str, float | None]] = [
    ("/points", "sensor_msgs/msg/PointCloud2", 10.0),
    ("/camera/image_raw", "sensor_msgs/msg/Image", 30.0),
    ("/camera/image_raw/compressed", "sensor_msgs/msg/CompressedImage", 30.0),
    ("/imu/data", "sensor_msgs/msg/Imu", 200.0),
    ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", 2.0),
    ("/rosout", "rcl_interfaces/msg/Log", None),
    ("/plan", "nav_msgs/msg/Path", 5.0),
    ("/markers", "visualization_msgs/msg/MarkerArray", 2.0),
    ("/map", "nav_msgs/msg/OccupancyGrid", None),
    ("/rg/sensors/front/lidar/scan", "sensor_msgs/msg/LaserScan", 10.0),
    ("/rg/driver/state", "std_msgs/msg/String", 10.0),
    ("/goals", "nav_msgs/msg/Goals", 1.0),
    ("/odom", "nav_msgs/msg/Odometry", 50.0),
    ("/battery", "sensor_msgs/msg/BatteryState", 1.0),
]


# -- the publishers (run as ``robot_graph.py --publishers ARGS_JSON``) ---------------------


def run_publishers(args: dict[str, Any]) -> None:
    """Publish the graph until stdin closes; print JSON lines (ready, counts)."""
    import math
    import threading

    import rclpy
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import Point, PoseStamped, TransformStamped
    from nav_msgs.msg import Goals, OccupancyGrid, Odometry
    from nav_msgs.msg import Path as NavPath
    from rcl_interfaces.msg import Log
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import (
        BatteryState,
        CompressedImage,
        Image,
        Imu,
        LaserScan,
        PointCloud2,
        PointField,
    )
    from std_msgs.msg import String
    from tf2_msgs.msg import TFMessage
    from visualization_msgs.msg import Marker, MarkerArray

    rclpy.init()
    reliable = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                          reliability=ReliabilityPolicy.RELIABLE)
    best_effort = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                             reliability=ReliabilityPolicy.BEST_EFFORT)
    latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node = rclpy.create_node("robot_graph")
    driver = rclpy.create_node("driver", namespace="/rg")
    nodes = [node, driver]
    counts: Counter[str] = Counter()

    def tf_messages() -> list[bytes]:
        out = []
        for step in range(100):
            transforms = []
            for i in range(40):
                t = TransformStamped()
                t.header.frame_id = "base_link" if i else "odom"
                t.child_frame_id = f"link_{i}" if i else "base_link"
                moving = i < 8  # wheels, odom, a pan-tilt: the rest is fixed joints
                t.transform.translation.x = 0.1 * i + (0.02 * step if moving else 0.0)
                t.transform.rotation.z = math.sin(0.01 * step if moving else 0.0)
                t.transform.rotation.w = math.cos(0.01 * step if moving else 0.0)
                transforms.append(t)
            out.append(serialize_message(TFMessage(transforms=transforms)))
        return out

    def cloud() -> bytes:
        points = 300_000 // 16
        msg = PointCloud2(height=1, width=points, point_step=16, row_step=16 * points,
                          is_dense=True)
        msg.header.frame_id = "lidar"
        msg.fields = [PointField(name=n, offset=4 * k, datatype=PointField.FLOAT32, count=1)
                      for k, n in enumerate("xyz")] + [
            PointField(name="intensity", offset=12, datatype=PointField.FLOAT32, count=1)]
        msg.data = os.urandom(16 * points)
        return serialize_message(msg)

    def image() -> bytes:
        msg = Image(height=480, width=640, encoding="rgb8", step=640 * 3)
        msg.header.frame_id = "camera"
        msg.data = bytes(range(256)) * (640 * 480 * 3 // 256)
        return serialize_message(msg)

    def compressed() -> bytes:
        msg = CompressedImage(format="jpeg")
        msg.header.frame_id = "camera"
        msg.data = os.urandom(60_000)
        return serialize_message(msg)

    def diagnostics(source: str) -> bytes:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        statuses = [DiagnosticStatus(
            level=b"\x00", name=f"{source}: device {k}", message="OK",
            hardware_id=f"hw{k}",
            values=[KeyValue(key=f"key{j}", value=f"{j * 1.5:.2f}") for j in range(6)])
            for k in range(20)]
        return serialize_message(DiagnosticArray(status=statuses))

    def path() -> bytes:
        msg = NavPath()
        msg.header.frame_id = "map"
        msg.poses = [PoseStamped() for _ in range(2000)]
        for k, pose in enumerate(msg.poses):
            pose.header.frame_id = "map"
            pose.pose.position.x = 0.05 * k
        return serialize_message(msg)

    def markers() -> bytes:
        out = MarkerArray()
        for k in range(300):
            m = Marker(ns="obstacles", id=k, type=Marker.LINE_STRIP, action=Marker.ADD)
            m.header.frame_id = "map"
            m.scale.x = 0.05
            m.color.r = m.color.a = 1.0
            m.points = [Point(x=0.1 * j, y=0.1 * k, z=0.0) for j in range(50)]
            out.markers.append(m)
        return serialize_message(out)

    def big_map(cells: int) -> bytes:
        grid = OccupancyGrid()
        grid.header.frame_id = "map"
        grid.info.width = grid.info.height = cells
        grid.info.resolution = 0.05
        # Free space with walls every 50 cells and unknown borders, as a SLAM map looks.
        row = bytearray(b"\x00" * cells)
        row[::50] = b"\x64" * len(row[::50])
        wall = b"\x64" * cells
        rows = [wall if r % 50 == 0 else bytes(row) for r in range(cells)]
        grid.data = b"".join(rows)
        return serialize_message(grid)

    def scan() -> bytes:
        msg = LaserScan(angle_min=-3.14, angle_max=3.14, angle_increment=6.28 / 720,
                        range_min=0.1, range_max=30.0)
        msg.header.frame_id = "front_lidar"
        msg.ranges = [1.0 + (i % 97) * 0.03 for i in range(720)]
        return serialize_message(msg)

    def goals() -> bytes:
        msg = Goals()
        msg.goals = [PoseStamped() for _ in range(3)]
        return serialize_message(msg)

    def log_line(k: int) -> bytes:
        return serialize_message(Log(stamp=Time(sec=k), level=Log.INFO, name="flooder",
                                     msg=f"controller: cycle {k} took too long",
                                     file="controller.cpp", function="tick", line=42))

    fixed: dict[str, tuple[Any, list[bytes]]] = {}

    def publisher(name: str, cls: Any, qos: QoSProfile, payloads: list[bytes],
                  on: Any = None) -> None:
        topic = name.split("#")[0]  # "/battery#2": a second publisher of /battery
        fixed[name] = ((on or node).create_publisher(cls, topic, qos), payloads)

    publisher("/tf", TFMessage, QoSProfile(depth=100), tf_messages())
    publisher("/points", PointCloud2, best_effort, [cloud()])
    publisher("/camera/image_raw", Image, best_effort, [image()])
    publisher("/camera/image_raw/compressed", CompressedImage, best_effort, [compressed()])
    publisher("/imu/data", Imu, best_effort, [serialize_message(Imu())])
    with contextlib.suppress(ImportError):
        from diagnostic_msgs.msg import DiagnosticArray

        publisher("/diagnostics", DiagnosticArray, reliable, [diagnostics("aggregator")])
        second = rclpy.create_node("diagnostic_updater")
        nodes.append(second)
        publisher("/diagnostics#2", DiagnosticArray, reliable, [diagnostics("driver")],
                  on=second)
    publisher("/plan", NavPath, reliable, [path()])
    publisher("/markers", MarkerArray, reliable, [markers()])
    publisher("/rg/sensors/front/lidar/scan", LaserScan, best_effort, [scan()])
    publisher("/goals", Goals, reliable, [goals()])
    publisher("/battery", BatteryState, reliable,
              [serialize_message(BatteryState(percentage=0.8))])
    # A second type on /battery: DDS refuses it in the same participant, so another process.
    volts = subprocess.Popen([sys.executable, "-c", BATTERY_VOLTS], stdin=subprocess.PIPE)
    state = driver.create_publisher(String, "~/state", reliable)
    fixed["/rg/driver/state"] = (state, [serialize_message(String(data="driving"))])
    rosout = node.create_publisher(Log, "/rosout", QoSProfile(depth=1000))
    # /tf_static: three latched publishers, as robot_state_publisher and two drivers.
    statics = []
    for k in range(3):
        static_node = rclpy.create_node(f"static_{k}")
        nodes.append(static_node)
        statics.append(static_node.create_publisher(TFMessage, "/tf_static", latched))
        t = TransformStamped()
        t.header.frame_id = "base_link"
        t.child_frame_id = f"static_{k}"
        t.transform.rotation.w = 1.0
        statics[-1].publish(TFMessage(transforms=[t]))
    map_pub = node.create_publisher(OccupancyGrid, "/map", latched)
    map_cdr = big_map(int(args["map_cells"]))
    map_pub.publish(map_cdr)
    counts["/map"] = 1
    rates = {"/tf": 100.0, "/points": 10.0, "/camera/image_raw": args["image_rate_hz"],
             "/camera/image_raw/compressed": 30.0, "/imu/data": 200.0, "/diagnostics": 1.0,
             "/diagnostics#2": 1.0, "/plan": args["plan_hz"], "/markers": args["markers_hz"],
             "/rg/sensors/front/lidar/scan": 10.0, "/goals": 1.0, "/battery": 1.0,
             "/rg/driver/state": 10.0}
    for name, rate in rates.items():
        if name not in fixed or rate <= 0:
            continue
        pub, payloads = fixed[name]

        def tick(pub: Any = pub, payloads: list[bytes] = payloads, name: str = name) -> None:
            pub.publish(payloads[counts[name] % len(payloads)])
            counts[name] += 1

        node.create_timer(1.0 / rate, tick)
    # /odom: BEST_EFFORT at 50 Hz, its publisher destroyed and made again every 5 s.
    odom_state: dict[str, Any] = {"pub": None, "since": 0.0}
    odom_cdr = serialize_message(Odometry())

    def odom_tick() -> None:
        now = time.monotonic()
        if now - odom_state["since"] > 5.0:
            odom_state["since"] = now
            if odom_state["pub"] is None:
                odom_state["pub"] = node.create_publisher(Odometry, "/odom", best_effort)
            else:
                node.destroy_publisher(odom_state["pub"])
                odom_state["pub"] = None
        if odom_state["pub"] is not None:
            odom_state["pub"].publish(odom_cdr)
            counts["/odom"] += 1

    node.create_timer(0.02, odom_tick)
    flood = [log_line(k) for k in range(100)]
    stop = threading.Event()

    def flood_rosout() -> None:
        per_tick = max(1, int(args["rosout_per_s"]) // 100)
        next_t = time.monotonic()
        while not stop.is_set():
            for k in range(per_tick):
                rosout.publish(flood[k % len(flood)])
            counts["/rosout"] += per_tick
            next_t += 0.01
            stop.wait(max(0.0, next_t - time.monotonic()))

    if args["rosout_per_s"] > 0:
        threading.Thread(target=flood_rosout, daemon=True).start()
    executor = MultiThreadedExecutor(num_threads=2)
    for n in nodes:
        executor.add_node(n)
    threading.Thread(target=executor.spin, daemon=True).start()
    print(json.dumps({"ready": True, "map_bytes": len(map_cdr)}), flush=True)
    for line in sys.stdin:
        if line.strip() == "counts":
            print(json.dumps({"counts": dict(counts)}), flush=True)
    stop.set()
    volts.terminate()


# A node that publishes std_msgs/Float32 on /battery (a voltage), beside BatteryState.
BATTERY_VOLTS = """
import sys, threading, rclpy
from std_msgs.msg import Float32
rclpy.init()
node = rclpy.create_node("battery_volts")
pub = node.create_publisher(Float32, "/battery", 10)
node.create_timer(1.0, lambda: pub.publish(Float32(data=24.1)))
threading.Thread(target=rclpy.spin, args=(node,), daemon=True).start()
sys.stdin.read()
"""


# -- the measuring side --------------------------------------------------------------------


def sha(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


HEAVY_TOPICS = ("/plan", "/markers")  # arrays of messages: converted element by element


def write_configs(root: Path, port: int, heavy_rate_limit_hz: float | None = None) -> None:
    import yaml

    (root / "server.yaml").write_text(yaml.safe_dump({
        "listen_host": "127.0.0.1", "listen_port": port, "auth_map": "auth.yaml",
        "database": "fleet.db"}))
    (root / "auth.yaml").write_text(yaml.safe_dump({"version": 1, "identities": [
        {"name": ROBOT, "ip": ROBOT_IP, "rules": [{"topic": f"/{ROBOT}/.*", "op": "send"}]},
        {"name": "consumer", "token_sha256": sha(CONSUMER_TOKEN),
         "rules": [{"topic": ".*", "op": "receive"}]}]}))
    import importlib.util

    have_diagnostics = importlib.util.find_spec("diagnostic_msgs") is not None
    publish: list[dict[str, Any]] = [{"topic": topic, "type": type_name}
                                     for topic, type_name, _ in TOPICS
                                     if have_diagnostics or topic != "/diagnostics"]
    for entry in publish:
        if heavy_rate_limit_hz and entry["topic"] in HEAVY_TOPICS:
            entry["rate_limit_hz"] = heavy_rate_limit_hz
    (root / "client.yaml").write_text(yaml.safe_dump({
        "server_url": f"ws://127.0.0.1:{port}/", "robot_name": ROBOT,
        "bind_address": ROBOT_IP, "publish": publish, "tf": {},
        "status": {"period_s": 1.0}}, sort_keys=False))


def cpu_ticks(pid: int) -> int:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])  # utime + stime


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def metrics(port: int) -> dict[str, float]:
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    out: dict[str, float] = {}
    for line in text.splitlines():
        if line.startswith(("fleetctl_drops_total", "fleetctl_messages_in_total",
                            "fleetctl_errors_total", "fleetctl_closes_total")):
            name, _, value = line.rpartition(" ")
            out[name] = float(value)
    return out


LATENCY_TOPICS = (f"/{ROBOT}/imu/data", f"/{ROBOT}/odom", f"/{ROBOT}/status")


async def frames_until(ws: Any, deadline: float) -> AsyncIterator[str | bytes]:
    """The frames *ws* receives until *deadline* (``time.monotonic()``), one ``wait_for``
    a receive: the receive path the latency figures of docs/benchmarks.md were measured
    with."""
    while (left := deadline - time.monotonic()) > 0:
        try:
            frame = await asyncio.wait_for(ws.recv(), left)
        except TimeoutError:
            return
        yield frame


def whole_messages_until(ws: Any, deadline: float) -> AsyncIterator[bytes]:
    """The whole binary messages *ws* receives until *deadline*, fragmented ones
    reassembled (64 MiB, 30 s)."""
    from fleetctl.wire.fragments import Reassembler
    from fleetctl.wire.whole_messages import whole_messages

    return whole_messages(frames_until(ws, deadline), Reassembler(64 << 20, 30.0))


async def consume(port: int, seconds: float, counts: Counter[str],
                  sizes: dict[str, int], latencies_ms: list[float]) -> None:
    """A viewer subscribed to all of the robot's topics; counts whole messages per topic
    and the latency (robot's take -> here, one clock) of the small ones."""
    from websockets.asyncio.client import connect

    from fleetctl.wire.control import encode_subscription
    from fleetctl.wire.metadata import read_metadata

    deadline = time.monotonic() + seconds
    async with connect(f"ws://127.0.0.1:{port}/", max_size=None, ping_interval=None,
                       additional_headers={"Authorization": f"Bearer {CONSUMER_TOKEN}"}) as ws:
        await ws.send(encode_subscription(f"/{ROBOT}/.*"))
        async for message in whole_messages_until(ws, deadline):
            meta = read_metadata(message)
            counts[meta.topic] += 1
            sizes[meta.topic] = len(message)
            if meta.topic in LATENCY_TOPICS and meta.publish_time_ns:
                latencies_ms.append((time.time_ns() - meta.publish_time_ns) / 1e6)


async def foxglove(port: int, seconds: float, counts: Counter[str]) -> None:
    """A Foxglove WebSocket viewer (as Foxglove Studio speaks it) subscribed to every
    channel the relay advertises: the relay transcodes what it gets to CDR."""
    from websockets.asyncio.client import connect

    deadline = time.monotonic() + seconds
    subscribed: dict[int, str] = {}
    async with connect(f"ws://127.0.0.1:{port}/", max_size=None, ping_interval=None,
                       subprotocols=["foxglove.websocket.v1"],  # type: ignore[list-item]
                       additional_headers={"Authorization": f"Bearer {CONSUMER_TOKEN}"}) as ws:
        while (left := deadline - time.monotonic()) > 0:
            try:
                message = await asyncio.wait_for(ws.recv(), left)
            except TimeoutError:
                break
            if isinstance(message, bytes):
                if message[:1] == b"\x01":
                    counts[subscribed.get(int.from_bytes(message[1:5], "little"), "?")] += 1
                continue
            data = json.loads(message)
            if data.get("op") == "advertise":
                subs = []
                for channel in data["channels"]:
                    sub_id = len(subscribed) + 1
                    subscribed[sub_id] = channel["topic"]
                    subs.append({"id": sub_id, "channelId": channel["id"]})
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))


async def late_map(port: int, timeout_s: float) -> dict[str, Any]:
    """A viewer that subscribes to the map only now: how long until it has it, how big."""
    from websockets.asyncio.client import connect

    from fleetctl.wire.control import encode_subscription
    from fleetctl.wire.metadata import read_metadata

    start = time.monotonic()
    async with connect(f"ws://127.0.0.1:{port}/", max_size=None, ping_interval=None,
                       additional_headers={"Authorization": f"Bearer {CONSUMER_TOKEN}"}) as ws:
        await ws.send(encode_subscription(f"/{ROBOT}/map"))
        async for message in whole_messages_until(ws, start + timeout_s):
            meta = read_metadata(message)
            return {"received": True, "after_s": round(time.monotonic() - start, 2),
                    "frame_bytes": len(message), "type": meta.type, "latched": meta.latched}
    return {"received": False, "after_s": round(time.monotonic() - start, 2)}


def log_lines(path: Path) -> list[str]:
    """The client's WARNING/ERROR lines, numbers blurred so repeats count once."""
    seen: Counter[str] = Counter()
    for line in path.read_text(errors="replace").splitlines():
        if " WARNING " in line or " ERROR " in line or "Traceback" in line:
            key = re.sub(r"\d+(\.\d+)?", "N", line.split(" ", 2)[-1])[:220]
            seen[key] += 1
    return [f"{n}x {key}" for key, n in seen.most_common()]


class Procs:
    def __init__(self) -> None:
        self.procs: list[subprocess.Popen[bytes]] = []

    def start(self, argv: list[str], log: Path, env: dict[str, str] | None = None,
              stdin: int | None = subprocess.DEVNULL,
              stdout: int | None = None) -> subprocess.Popen[bytes]:
        proc = subprocess.Popen(argv, cwd=REPO, env={**os.environ, **(env or {})},
                                stdin=stdin, stdout=stdout or log.open("ab"),
                                stderr=log.open("ab"), start_new_session=True)
        self.procs.append(proc)
        return proc

    def stop(self) -> None:
        for proc in reversed(self.procs):
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()


def wait_until(check: Any, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise SystemExit(f"timed out waiting for {what}")
        time.sleep(0.1)


def read_json_line(proc: subprocess.Popen[bytes], key: str, timeout_s: float) -> dict[str, Any]:
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise SystemExit("the publisher process ended")
        with contextlib.suppress(ValueError):
            data = json.loads(line)
            if key in data:
                return dict(data)
    raise SystemExit(f"no {key} line from the publishers")


def measure(args: argparse.Namespace, root: Path) -> dict[str, Any]:
    from fleetctl.demo.fleet import free_port
    from fleetctl.demo.run import http_ok, online_robots

    port = free_port()
    write_configs(root, port, args.heavy_rate_limit_hz)
    env = {"ROS_DOMAIN_ID": DOMAIN_ID}
    procs = Procs()
    try:
        server = procs.start([PY, "-m", "fleetctl.cli.main", "server", "--config",
                              str(root / "server.yaml")], root / "server.log")
        wait_until(lambda: http_ok(f"http://127.0.0.1:{port}/healthz"), 30, "the relay")
        publishers = procs.start(
            [PY, str(Path(__file__).resolve()), "--publishers", json.dumps({
                "image_rate_hz": args.image_rate_hz, "rosout_per_s": args.rosout_per_s,
                "plan_hz": args.plan_hz, "markers_hz": args.markers_hz,
                "map_cells": args.map_cells})],
            root / "publishers.log", env, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        ready = read_json_line(publishers, "ready", 60)
        # As the robot bundle's fleetctl.env runs it (docs/robot.md, "Large messages").
        client_env = {**env, "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4?sockets_size=4194304"}
        client = procs.start([PY, "-m", "fleetctl.cli.main", "client", "--config",
                              str(root / "client.yaml"), "--print-stats"],
                             root / "client.log", client_env)
        wait_until(lambda: ROBOT in online_robots(f"http://127.0.0.1:{port}"), 60,
                   "the robot online")
        time.sleep(args.warmup_s)  # a benchmark's warm-up, not synchronisation
        counts: Counter[str] = Counter()
        fox_counts: Counter[str] = Counter()
        sizes: dict[str, int] = {}
        latencies: list[float] = []
        load_before = os.getloadavg()[0]
        link_mid: dict[str, Any] = {}
        samples: dict[str, list[int]] = {"client_rss_kb": [], "server_rss_kb": []}
        start_ticks = {p: cpu_ticks(p.pid) for p in (client, server, publishers)}
        t0 = time.monotonic()

        async def sample() -> None:
            while time.monotonic() - t0 < args.seconds:
                samples["client_rss_kb"].append(rss_kb(client.pid))
                samples["server_rss_kb"].append(rss_kb(server.pid))
                if not link_mid and time.monotonic() - t0 > args.seconds / 2:
                    client.send_signal(signal.SIGUSR1)  # the client logs its stats
                    link_mid["asked"] = True
                await asyncio.sleep(1.0)

        async def both() -> None:
            parts = [consume(port, args.seconds, counts, sizes, latencies), sample()]
            if args.foxglove:
                parts.append(foxglove(port, args.seconds, fox_counts))
            await asyncio.gather(*parts)

        asyncio.run(both())
        elapsed = time.monotonic() - t0
        cpu = {name: round(100.0 * (cpu_ticks(p.pid) - start_ticks[p]) / TICKS / elapsed, 1)
               for name, p in (("client", client), ("server", server),
                               ("publishers", publishers))}
        assert publishers.stdin is not None
        publishers.stdin.write(b"counts\n")
        publishers.stdin.flush()
        published = read_json_line(publishers, "counts", 10)["counts"]
        late = asyncio.run(late_map(port, 60.0))
        relay = metrics(port)
        client.send_signal(signal.SIGTERM)
        client.wait(30)
        stats_line = (root / "client.log").read_text(errors="replace").strip().splitlines()
        stats = next((json.loads(x) for x in reversed(stats_line) if x.startswith("{")), {})
        mid = next((json.loads(x.split(" stats: ", 1)[1]) for x in stats_line
                    if " stats: {" in x), {})
        latencies.sort()
        return {
            "seconds": round(elapsed, 1), "cpu_percent": cpu,
            "load_average_1min": [round(load_before, 1), round(os.getloadavg()[0], 1)],
            "client_rss_mb": {"peak": round(max(samples["client_rss_kb"]) / 1024, 1),
                              "end": round(samples["client_rss_kb"][-1] / 1024, 1)},
            "server_rss_mb": {"peak": round(max(samples["server_rss_kb"]) / 1024, 1),
                              "end": round(samples["server_rss_kb"][-1] / 1024, 1)},
            "map_cdr_bytes": ready["map_bytes"],
            "published": published,
            "received_per_s": {t: round(n / elapsed, 1) for t, n in sorted(counts.items())},
            "received_frame_bytes": dict(sorted(sizes.items())),
            "latency_ms_small_topics": {
                "n": len(latencies),
                "p50": round(latencies[len(latencies) // 2], 1) if latencies else None,
                "p99": round(latencies[int(len(latencies) * 0.99)], 1) if latencies else None},
            "foxglove_received_per_s": {t: round(n / elapsed, 1)
                                        for t, n in sorted(fox_counts.items())},
            "link_mid_run": {k: mid.get(k) for k in (
                "window_bytes", "last_rtt_ms", "min_rtt_ms", "delivery_rate_Bps",
                "link_rate_Bps", "connected", "reconnects", "link_timeouts")},
            "late_map": late,
            "relay_drops": {k: v for k, v in relay.items() if "drops" in k},
            "relay_errors": {k: v for k, v in relay.items() if "drops" not in k
                             and "messages_in" not in k},
            "client_bridge": {k: v for k, v in stats.get("bridge", {}).items()
                              if not isinstance(v, dict) or k.startswith("per_topic")},
            "client_warnings": log_lines(root / "client.log"),
            "server_warnings": log_lines(root / "server.log"),
        }
    finally:
        procs.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 2)[2])
    parser.add_argument("--seconds", type=float, default=60.0, help="measured window (60)")
    parser.add_argument("--warmup-s", type=float, default=10.0, help="before it (10)")
    parser.add_argument("--image-rate-hz", type=float, default=30.0,
                        help="raw 640x480 rgb8 images per second (30; 0: none)")
    parser.add_argument("--rosout-per-s", type=int, default=1000,
                        help="/rosout messages per second (1000)")
    parser.add_argument("--plan-hz", type=float, default=5.0,
                        help="nav_msgs/Path of 2,000 poses per second (5; 0: none)")
    parser.add_argument("--markers-hz", type=float, default=2.0,
                        help="MarkerArray of 300 x 50 points per second (2; 0: none)")
    parser.add_argument("--heavy-rate-limit-hz", type=float,
                        help="rate_limit_hz of the /plan and /markers entries (none)")
    parser.add_argument("--map-cells", type=int, default=4000, help="map side, cells (4000)")
    parser.add_argument("--foxglove", action="store_true",
                        help="also a Foxglove WebSocket viewer subscribed to every channel")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--keep", type=Path, help="keep configs and logs in this directory")
    parser.add_argument("--publishers", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.publishers is not None:
        run_publishers(json.loads(args.publishers))
        return
    with tempfile.TemporaryDirectory(prefix="robot-graph-") as tmp:
        root = args.keep or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        result = measure(args, root)
    text = json.dumps(result, indent=2)
    print(text)
    if args.json is not None:
        args.json.write_text(text + "\n")


if __name__ == "__main__":
    main()
