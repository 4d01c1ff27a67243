"""Long-run soak of the robot client (``fleetctl client``) under link churn.

Usage::

    .venv/bin/python benchmarks/soak_client.py [--minutes 4] [--warmup-s 60] [--json out.json]

A robot on LTE loses its link dozens of times a day and runs for weeks: does the client
keep memory, fds, threads or state that grows with reconnects or with time? Real parts
only: a ``fleetctl server`` process (killed and restarted), the real ``fleetctl client``
process (rclpy node), an rclpy process publishing ``/scan`` (LaserScan 10 Hz), ``/pose``
(PoseStamped 20 Hz), ``/events`` (String, ``no_drop``, 10 Hz, ``"1"``, ``"2"``, ...) and a
latched ``/map`` (OccupancyGrid, TRANSIENT_LOCAL) and listening to ``/cmd_pose``, which the
client receives from the relay as ``/soak/cmd`` (sent by the consumer at 2 Hz).

The client reaches the relay through a TCP proxy run here (no root, no netns), which can
stall every byte both ways (a cut: what was written arrives when the cut ends, as TCP
retransmission would deliver it), refuse connections, or reset them. The churn cycles
through: relay SIGKILL (down 2 s), relay SIGTERM and restart, a burst of 10 resets, a
1.5 s cut, a 20 s cut, 5 s of refused connections, the relay refusing the robot's token
for 20 s (its auth map rewritten without the robot, then restored: the relay re-reads it),
a session takeover (a second connection with the robot's token and session name), and the
``/scan`` publisher restarted with the other reliability (the client recreates its
subscription to match: a QoS switch).
A consumer with a session of its own (so the relay keeps its no_drop frames while it is
away) counts every topic and checks that ``/soak/events`` arrives complete and in order.

After every churn step and a settle time with the link up, a sample: the client's RSS
(``VmRSS``), open fds (and how many are sockets), threads, and its counters (SIGUSR1 makes
it log ``stats: {...}``). Growth is the least-squares slope over the samples after the
warm-up, per hour and per 100 reconnects; the verdict says whether any grows.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hashlib
import json
import os
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from websockets.asyncio.client import connect
from websockets.exceptions import WebSocketException

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
PY = sys.executable
ROBOT = "soak"
ROBOT_TOKEN = "soak-robot-token"
CONSUMER_TOKEN = "soak-consumer-token"
EVENTS = "/soak/events"
CMD = "/soak/cmd"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
RELAY_ADDR = "127.0.0.1"
# The proxy dials the relay from this address, so the robot's refused logins spend the
# failed-login budget of an address the consumer does not share.
PROXY_SOURCE = "127.0.0.7"

ROS_HELPER = """
import json, sys, threading, time, rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy, DurabilityPolicy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node("soak_robot")
reliable = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                      reliability=ReliabilityPolicy.RELIABLE)
latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
pose_pub = node.create_publisher(PoseStamped, "/pose", 10)
events_pub = node.create_publisher(String, "/events", reliable)
map_pub = node.create_publisher(OccupancyGrid, "/map", latched)
grid = OccupancyGrid()
grid.header.frame_id = "map"
grid.info.width = grid.info.height = 100
grid.info.resolution = 0.05
grid.data = [(i * 7) % 101 for i in range(100 * 100)]
map_pub.publish(grid)
pose = PoseStamped()
pose.header.frame_id = "map"
state = {"events": 0, "cmd": 0, "stop": False}
def stamp(msg):
    msg.header.stamp = node.get_clock().now().to_msg()
def on_pose():
    stamp(pose); pose.pose.position.x += 0.001; pose_pub.publish(pose)
def on_event():
    # no_drop events start 2 s after the client's subscription is matched here: DDS
    # matches each side separately, and a reader drops what a writer sent before the
    # reader matched it (lost before the client, not the client's to deliver).
    if state["stop"] or events_pub.get_subscription_count() == 0:
        return
    state.setdefault("matched", time.monotonic())
    if time.monotonic() - state["matched"] < 2.0:
        return
    state["events"] += 1
    events_pub.publish(String(data=str(state["events"])))
def on_cmd(msg):
    state["cmd"] += 1
def report():
    print(json.dumps({"events": state["events"], "cmd": state["cmd"]}), flush=True)
def read_stdin():
    for line in sys.stdin:
        if line.strip() == "stop-events":
            state["stop"] = True
node.create_subscription(PoseStamped, "/cmd_pose", on_cmd, 10)
node.create_timer(0.05, on_pose)
node.create_timer(0.1, on_event)
node.create_timer(1.0, report)
threading.Thread(target=read_stdin, daemon=True).start()
print(json.dumps({"ready": True}), flush=True)
rclpy.spin(node)
"""

# /scan comes from a process of its own, restarted with the other reliability by a churn
# step: the client recreates its subscription to match (a QoS switch).
SCAN_HELPER = """
import sys, rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy
from sensor_msgs.msg import LaserScan
rclpy.init()
node = rclpy.create_node("soak_scan")
reliability = ReliabilityPolicy.RELIABLE if sys.argv[1] == "reliable" else \\
    ReliabilityPolicy.BEST_EFFORT
pub = node.create_publisher(LaserScan, "/scan", QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=10, reliability=reliability))
scan = LaserScan()
scan.header.frame_id = "laser"
scan.angle_min, scan.angle_max, scan.angle_increment = -3.14, 3.14, 6.28 / 720
scan.range_min, scan.range_max = 0.1, 30.0
scan.ranges = [1.0 + (i % 97) * 0.03 for i in range(720)]
def on_scan():
    scan.header.stamp = node.get_clock().now().to_msg()
    pub.publish(scan)
node.create_timer(0.1, on_scan)
rclpy.spin(node)
"""


def sha(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def auth_map(with_robot: bool) -> dict[str, Any]:
    identities: list[dict[str, Any]] = [
        {"name": "consumer", "token_sha256": sha(CONSUMER_TOKEN),
         "rules": [{"topic": ".*", "op": "receive"}, {"topic": CMD, "op": "send"}]}]
    if with_robot:
        identities.append({"name": ROBOT, "token_sha256": sha(ROBOT_TOKEN),
                           "rules": [{"topic": "/soak/.*", "op": "send"},
                                     {"topic": "/robots/.*", "op": "send"},
                                     {"topic": CMD, "op": "receive"}]})
    return {"version": 1, "identities": identities}


def write_atomic(path: Path, data: Any) -> None:
    """Replace *path* by rename (a new inode: what the relay's reload watches for)."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    tmp.replace(path)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind((RELAY_ADDR, 0))
        return int(sock.getsockname()[1])


# -- the proxy between the client and the relay ------------------------------------------


class Proxy:
    """A TCP proxy that can stall every byte (a cut), refuse, or reset (RST) connections."""

    def __init__(self, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        self.flowing = asyncio.Event()
        self.flowing.set()
        self.conns: set[tuple[socket.socket, ...]] = set()
        self.server: asyncio.Server | None = None
        self.port = 0
        self.accepted = 0

    async def start(self, port: int = 0) -> None:
        self.server = await asyncio.start_server(self._serve, RELAY_ADDR, port)
        self.port = self.server.sockets[0].getsockname()[1]

    async def refuse(self) -> None:
        """Stop listening (new dials are refused) and reset every connection."""
        assert self.server is not None
        self.server.close()
        self.reset_all()
        await self.server.wait_closed()

    def reset_all(self) -> None:
        for pair in list(self.conns):
            for sock in pair:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER,
                                    struct.pack("ii", 1, 0))
                    sock.shutdown(socket.SHUT_RDWR)  # RST (linger 0) wakes both pumps
        self.conns.clear()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.accepted += 1
        down: socket.socket = writer.get_extra_info("socket")
        pair: tuple[socket.socket, ...] = (down,)
        self.conns.add(pair)
        try:
            await self.flowing.wait()  # a dial during a cut waits for the path, as a SYN would
            if pair not in self.conns:
                return
            up_reader, up_writer = await asyncio.open_connection(
                RELAY_ADDR, self.upstream_port, local_addr=(PROXY_SOURCE, 0))
        except OSError:
            self.conns.discard(pair)
            writer.transport.abort()
            return
        self.conns.discard(pair)
        pair = (down, up_writer.get_extra_info("socket"))
        self.conns.add(pair)
        await asyncio.gather(self._pump(reader, up_writer), self._pump(up_reader, writer),
                             return_exceptions=True)
        self.conns.discard(pair)
        writer.transport.abort()
        up_writer.transport.abort()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while data := await reader.read(65536):
                await self.flowing.wait()
                writer.write(data)
                await writer.drain()
        finally:
            writer.transport.abort()


# -- the consumer --------------------------------------------------------------------------


@dataclass
class Consumer:
    """Counts every topic from the relay (its own session) and checks /soak/events' order."""

    url: str
    frames: dict[str, int] = field(default_factory=dict)
    events: list[int] = field(default_factory=list)
    event_times: list[float] = field(default_factory=list)  # wall clock of each arrival
    cmd_sent: int = 0
    connects: int = 0

    async def run(self) -> None:
        from fleetctl.wire.codec import default_codec
        from fleetctl.wire.control import encode_subscription
        from fleetctl.wire.metadata import read_metadata
        from fleetctl.wire.whole_messages import whole_messages

        codec = default_codec()
        while True:
            try:
                async with connect(self.url, ping_interval=None, additional_headers={
                        "Authorization": f"Bearer {CONSUMER_TOKEN}",
                        "X-Fleetctl-Session": "soak-consumer"}) as ws:
                    self.connects += 1
                    await ws.send(encode_subscription("/soak/.*"))
                    sender = asyncio.create_task(self._send_cmd(ws, codec))
                    try:
                        async for whole in whole_messages(ws):
                            meta = read_metadata(whole)
                            self.frames[meta.topic] = self.frames.get(meta.topic, 0) + 1
                            if meta.topic == EVENTS:
                                self.events.append(int(codec.decode(whole)[1].data))
                                self.event_times.append(time.time())
                    finally:
                        sender.cancel()
            except (TimeoutError, OSError, WebSocketException):
                pass
            await asyncio.sleep(0.2)  # the relay is down: redial at 5 Hz

    async def _send_cmd(self, ws: Any, codec: Any) -> None:
        msg = _pose()
        while True:
            self.cmd_sent += 1
            await ws.send(codec.encode(msg, POSE_TYPE, CMD, seq=self.cmd_sent,
                                       publish_time_ns=time.time_ns()))
            await asyncio.sleep(0.5)  # the operator's 2 Hz command stream

    def order_report(self) -> dict[str, Any]:
        seen: set[int] = set()
        duplicates = reorders = 0
        last = 0
        for n in self.events:
            if n in seen:
                duplicates += 1
                continue
            seen.add(n)
            if n < last:
                reorders += 1
            last = max(last, n)
        top = max(seen, default=0)
        gaps: list[tuple[int, int]] = []  # (first missing, how many), the first ten
        previous = 0
        for n in sorted(seen):
            if n > previous + 1 and len(gaps) < 10:
                gaps.append((previous + 1, n - previous - 1))
            previous = n
        return {"received": len(self.events), "unique": len(seen), "duplicates": duplicates,
                "reorders": reorders, "missing": top - len(seen), "highest": top,
                "gaps": gaps}


def _pose() -> Any:
    """A PoseStamped of the type store's own classes (no rclpy in this process)."""
    from rosbags.typesys.stores.ros2_jazzy import builtin_interfaces__msg__Time as Time
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Point as Point
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Pose as Pose
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__PoseStamped as Stamped
    from rosbags.typesys.stores.ros2_jazzy import geometry_msgs__msg__Quaternion as Quat
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__Header as Header

    return Stamped(Header(Time(0, 0), "map"),
                   Pose(Point(1.0, 2.0, 0.0), Quat(0.0, 0.0, 0.0, 1.0)))


# -- processes -------------------------------------------------------------------------------


class Relay:
    """The ``fleetctl server`` process on a fixed port, restartable (its SQLite file keeps
    the sessions across restarts)."""

    def __init__(self, work: Path, port: int) -> None:
        self.work, self.port = work, port
        (work / "server.yaml").write_text(json.dumps({
            "listen_host": RELAY_ADDR, "listen_port": port, "auth_map": "auth.yaml",
            "database": "fleet.db"}))
        write_atomic(work / "auth.yaml", auth_map(True))
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0

    async def start(self) -> None:
        self.starts += 1
        log = (self.work / "server.log").open("ab")
        self.proc = subprocess.Popen(
            [str(Path(PY).parent / "fleetctl"), "server", "--config",
             str(self.work / "server.yaml")], stdout=log, stderr=log, start_new_session=True)
        await poll(lambda: http_ok(f"http://{RELAY_ADDR}:{self.port}/healthz"), 30.0,
                   "the relay to listen")

    async def stop(self, signum: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(signum)
        await asyncio.to_thread(self.proc.wait, 30)


def http_ok(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=1.0) as response:
            return int(response.status) == 200
    except OSError:
        return False


async def poll(check: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Wait until *check()* holds, polling every 50 ms; fail after *timeout_s*."""
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise SystemExit(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.05)  # another process's state, polled with a deadline


class ClientProc:
    """The ``fleetctl client`` process; :meth:`sample` reads /proc and its SIGUSR1 stats."""

    def __init__(self, work: Path, url: str, env: dict[str, str], log_level: str) -> None:
        (work / "token").write_text(ROBOT_TOKEN)
        (work / "client.yaml").write_text(json.dumps({
            "server_url": url, "robot_name": ROBOT, "token_file": str(work / "token"),
            "publish": [
                {"topic": "/scan", "type": "sensor_msgs/msg/LaserScan",
                 "remote_topic": "/soak/scan"},
                {"topic": "/pose", "type": POSE_TYPE, "remote_topic": "/soak/pose"},
                {"topic": "/events", "type": "std_msgs/msg/String",
                 "remote_topic": EVENTS, "no_drop": True},
                {"topic": "/map", "type": "nav_msgs/msg/OccupancyGrid",
                 "remote_topic": "/soak/map"}],
            "subscribe": [{"remote_topic": CMD, "type": POSE_TYPE,
                           "local_topic": "/cmd_pose"}]}))
        self.log_path = work / "client.log"
        self.proc = subprocess.Popen(
            [str(Path(PY).parent / "fleetctl"), "client", "--config", str(work / "client.yaml"),
             "--log-level", log_level],
            env=env, stdout=subprocess.DEVNULL, stderr=self.log_path.open("ab"),
            start_new_session=True)
        self._read_at = 0

    async def stats(self) -> dict[str, Any]:
        """SIGUSR1, then the ``stats: {...}`` line it logs (within 10 s)."""
        self.proc.send_signal(signal.SIGUSR1)
        found: dict[str, Any] | None = None

        def logged() -> bool:
            nonlocal found
            with self.log_path.open("rb") as f:
                f.seek(self._read_at)
                data = f.read()
            end = data.rfind(b"\n")
            if end < 0:
                return False
            for line in data[:end].splitlines():
                marker = line.find(b"stats: {")
                if marker >= 0:
                    found = json.loads(line[marker + 7:])
            self._read_at += end + 1
            return found is not None

        await poll(logged, 10.0, "the client's stats line")
        assert found is not None
        return found

    def proc_figures(self) -> dict[str, float]:
        pid = self.proc.pid
        rss = 0.0
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) / 1024
        fds = os.listdir(f"/proc/{pid}/fd")
        sockets = 0
        for fd in fds:
            with contextlib.suppress(OSError):
                sockets += os.readlink(f"/proc/{pid}/fd/{fd}").startswith("socket:")
        return {"rss_mb": rss, "fds": len(fds), "sockets": sockets,
                "threads": len(os.listdir(f"/proc/{pid}/task"))}


# -- churn ---------------------------------------------------------------------------------


class ScanPublisher:
    """The /scan publisher process, restartable with the other reliability."""

    def __init__(self, env: dict[str, str], work: Path) -> None:
        self.env, self.work = env, work
        self.reliable = True
        self.proc = self._start()

    def _start(self) -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            [PY, "-c", SCAN_HELPER, "reliable" if self.reliable else "best-effort"],
            env=self.env, stdout=subprocess.DEVNULL,
            stderr=(self.work / "scan.log").open("ab"), start_new_session=True)

    async def switch(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        await asyncio.to_thread(self.proc.wait, 15)
        self.reliable = not self.reliable
        self.proc = self._start()

    def stop(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()


@dataclass
class Soak:
    relay: Relay
    proxy: Proxy
    work: Path
    scan: ScanPublisher

    async def relay_sigkill(self) -> None:
        await self.relay.stop(signal.SIGKILL)
        await asyncio.sleep(2.0)  # the relay is down for 2 s (churn timing, not a sync)
        await self.relay.start()

    async def relay_restart(self) -> None:
        await self.relay.stop(signal.SIGTERM)
        await self.relay.start()

    async def resets(self) -> None:
        for _ in range(10):
            self.proxy.reset_all()
            await asyncio.sleep(1.0)  # one reset a second (churn timing)

    async def cut(self, seconds: float) -> None:
        self.proxy.flowing.clear()
        await asyncio.sleep(seconds)  # the cut's length (churn timing)
        self.proxy.flowing.set()

    async def short_cut(self) -> None:
        await self.cut(1.5)

    async def long_cut(self) -> None:
        await self.cut(20.0)

    async def refused(self) -> None:
        await self.proxy.refuse()
        await asyncio.sleep(5.0)  # refused for 5 s (churn timing)
        await self.proxy.start(self.proxy.port)

    async def auth_refused(self) -> None:
        write_atomic(self.work / "auth.yaml", auth_map(False))
        await asyncio.sleep(20.0)  # the token refused for 20 s (churn timing)
        write_atomic(self.work / "auth.yaml", auth_map(True))

    async def takeover(self) -> None:
        url = f"ws://{RELAY_ADDR}:{self.relay.port}/"
        with contextlib.suppress(TimeoutError, OSError, WebSocketException):
            async with connect(url, ping_interval=None, additional_headers={
                    "Authorization": f"Bearer {ROBOT_TOKEN}",
                    "X-Fleetctl-Session": ROBOT}) as ws:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(ws.recv(), 2.0)  # hold the session ~2 s

    def steps(self) -> list[tuple[str, Callable[[], Awaitable[None]]]]:
        return [("relay SIGKILL, down 2 s", self.relay_sigkill),
                ("relay SIGTERM + restart", self.relay_restart),
                ("10 resets, 1 s apart", self.resets),
                ("cut 1.5 s", self.short_cut),
                ("cut 20 s", self.long_cut),
                ("refused 5 s", self.refused),
                ("token refused 20 s", self.auth_refused),
                ("session takeover", self.takeover),
                ("/scan publisher QoS switch", self.scan.switch)]


async def soak(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(REPO),
           "ROS_DOMAIN_ID": str(args.domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    relay = Relay(work, free_port())
    await relay.start()
    proxy = Proxy(relay.port)
    await proxy.start()
    consumer = Consumer(f"ws://{RELAY_ADDR}:{relay.port}/")
    consumer_task = asyncio.create_task(consumer.run())
    ros = subprocess.Popen([PY, "-c", ROS_HELPER], env=env, stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, stderr=(work / "ros.log").open("ab"),
                           start_new_session=True)
    scan = ScanPublisher(env, work)
    client = ClientProc(work, f"ws://{RELAY_ADDR}:{proxy.port}/", env, args.client_log_level)
    ros_state: dict[str, int] = {}

    def read_ros() -> None:
        assert ros.stdout is not None
        for line in ros.stdout:
            ros_state.update(json.loads(line))

    reader = asyncio.create_task(asyncio.to_thread(read_ros))
    samples: list[dict[str, Any]] = []
    driver = Soak(relay, proxy, work, scan)
    try:
        await poll(lambda: consumer.frames.get(EVENTS, 0) > 0, 90.0, "the first event")
        t0 = time.monotonic()
        end = t0 + args.minutes * 60
        steps = driver.steps()
        if args.steps:
            steps = [steps[int(i)] for i in args.steps.split(",")]
        i = 0
        while time.monotonic() < end:
            name, step = steps[i % len(steps)]
            i += 1
            await step()
            await asyncio.sleep(args.settle_s)  # the link up for a while before sampling
            stats = await client.stats()
            order = consumer.order_report()
            sample = {"t_s": time.monotonic() - t0, "after": name,
                      **client.proc_figures(), **pick(stats),
                      "events_missing": order["missing"], "events_highest": order["highest"]}
            samples.append(sample)
            print(row(sample), flush=True)
        # Drain: no more events, link up; every event must reach the consumer.
        assert ros.stdin is not None
        ros.stdin.write(b"stop-events\n")
        ros.stdin.flush()
        await asyncio.sleep(2.0)  # the helper's next report carries the final count
        published = ros_state.get("events", 0)
        with contextlib.suppress(SystemExit):  # a loss is a finding: report it
            await poll(lambda: len(set(consumer.events)) >= published, 60.0,
                       f"all {published} events at the consumer")
        final = await client.stats()
        drops = relay_drops(relay.port)
        around = gap_context(consumer)
        return {"samples": samples, "final_stats": final, "published_events": published,
                "cmd_sent": consumer.cmd_sent, "cmd_received_by_ros": ros_state.get("cmd", 0),
                "consumer_frames": consumer.frames, "consumer_connects": consumer.connects,
                "order": consumer.order_report(), "relay_starts": relay.starts,
                "relay_drops_since_last_start": drops, "gap_arrivals": around,
                "proxy_accepted": proxy.accepted}
    finally:
        consumer_task.cancel()
        for proc in (client.proc, ros):
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
        for proc in (client.proc, ros):
            try:
                await asyncio.to_thread(proc.wait, 15)
            except subprocess.TimeoutExpired:
                proc.kill()
        reader.cancel()
        scan.stop()
        if relay.proc is not None and relay.proc.poll() is None:
            await relay.stop(signal.SIGTERM)


def relay_drops(port: int) -> list[str]:
    """The relay's drop counters (``/metrics`` lines naming drops; loopback may read
    them), since its last start."""
    try:
        with urllib.request.urlopen(f"http://{RELAY_ADDR}:{port}/metrics", timeout=5) as r:
            text = r.read().decode()
    except OSError as exc:
        return [f"unreadable: {exc}"]
    return [line for line in text.splitlines()
            if "drop" in line and not line.startswith("#") and not line.endswith(" 0")]


def gap_context(consumer: Consumer) -> list[str]:
    """When the events on either side of each gap arrived (wall clock), to line a loss up
    with the churn step and the logs."""
    out = []
    for first, count in consumer.order_report()["gaps"]:
        for n in (first - 1, first + count):
            if n in consumer.events:
                at = consumer.event_times[consumer.events.index(n)]
                out.append(f"event {n} arrived {time.strftime('%H:%M:%S', time.gmtime(at))}"
                           f".{int(at % 1 * 1000):03d} UTC")
    return out


def pick(stats: dict[str, Any]) -> dict[str, Any]:
    """The counters the table shows and the growth fit reads."""
    standby = stats.get("standby") or {}
    received = stats.get("received") or {}
    return {"connects": stats.get("connects", 0), "reconnects": stats.get("reconnects", 0),
            "no_drop_queued": stats.get("no_drop_queued", 0),
            "no_drop_unacked": stats.get("no_drop_unacked", 0),
            "in_flight_frames": stats.get("in_flight_frames", 0),
            "standby_open": standby.get("open", 0), "standby_opened": standby.get("opened", 0),
            "received": received.get("frames", 0), "duplicates": received.get("duplicates", 0),
            "link_timeouts": stats.get("link_timeouts", 0),
            "connect_failures": stats.get("connect_failures", 0)}


HEADER = (f"{'t s':>6} {'after':26} {'RSS MB':>7} {'fds':>4} {'sock':>4} {'thr':>4} "
          f"{'conn':>5} {'fail':>5} {'ndq':>4} {'unack':>5} {'stby':>4} {'recv':>6} {'lost':>5}")


def row(s: dict[str, Any]) -> str:
    return (f"{s['t_s']:6.0f} {s['after'][:26]:26} {s['rss_mb']:7.1f} {s['fds']:4d} "
            f"{s['sockets']:4d} {s['threads']:4d} {s['connects']:5d} "
            f"{s['connect_failures']:5d} {s['no_drop_queued']:4d} {s['no_drop_unacked']:5d} "
            f"{s['standby_open']:4d} {s['received']:6d} {s['events_missing']:5d}")


def slope(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of ys over xs (0 with fewer than 2 points)."""
    if len(set(xs)) < 2:  # fewer than 2 points, or no spread to fit a slope on
        return 0.0
    return statistics.linear_regression(xs, ys).slope


def growth(samples: list[dict[str, Any]], warmup_s: float) -> dict[str, dict[str, float]]:
    steady = [s for s in samples if s["t_s"] >= warmup_s]
    out: dict[str, dict[str, float]] = {}
    for key in ("rss_mb", "fds", "sockets", "threads"):
        ys = [float(s[key]) for s in steady]
        per_s = slope([s["t_s"] for s in steady], ys)
        per_connect = slope([float(s["connects"]) for s in steady], ys)
        out[key] = {"per_hour": per_s * 3600, "per_100_connects": per_connect * 100,
                    "first": ys[0] if ys else 0.0, "last": ys[-1] if ys else 0.0,
                    "max": max(ys, default=0.0)}
    return out


def accounting(stats: dict[str, Any]) -> dict[str, dict[str, int]]:
    """Per topic: offered = sent once + dropped + still waiting (the residual)."""
    out = {}
    for topic, t in stats.get("topics", {}).items():
        dropped = sum(v for k, v in t.items() if k.startswith("dropped_"))
        out[topic] = {"offered": t["offered"], "sent": t["sent"], "requeued": t["requeued"],
                      "dropped": dropped, "acked": t.get("acked", 0),
                      "residual": t["offered"] - (t["sent"] - t["requeued"]) - dropped}
    return out


def report(res: dict[str, Any], args: argparse.Namespace) -> None:
    g = growth(res["samples"], args.warmup_s)
    final = res["final_stats"]
    print(f"\n{len(res['samples'])} samples over {args.minutes:.0f} min; relay started "
          f"{res['relay_starts']} times; client connects {final.get('connects')}, "
          f"connect failures {final.get('connect_failures')}, link timeouts "
          f"{final.get('link_timeouts')}, session resumes {final.get('session_resumes')}, "
          f"standby {final.get('standby')}")
    print(f"growth after {args.warmup_s:.0f} s warm-up (least squares):")
    for key, v in g.items():
        print(f"    {key:8s} {v['first']:8.1f} -> {v['last']:8.1f} (max {v['max']:.1f}): "
              f"{v['per_hour']:+8.2f} per hour, {v['per_100_connects']:+7.2f} per 100 connects")
    order = res["order"]
    print(f"no_drop {EVENTS}: published {res['published_events']}, consumer {order}")
    print(f"relay drop counters (since its last start): {res['relay_drops_since_last_start']}")
    print(f"arrivals around the gaps: {res['gap_arrivals']}")
    print(f"commands: consumer sent {res['cmd_sent']}, ROS got {res['cmd_received_by_ros']}, "
          f"client received frames {final.get('received', {}).get('frames')}")
    print("client accounting per topic (residual = offered - first sends - dropped):")
    for topic, a in accounting(final).items():
        print(f"    {topic:22s} {a}")
    print(f"consumer frames per topic: {res['consumer_frames']}")
    flat = (g["rss_mb"]["per_hour"] < args.rss_mb_per_hour
            and g["fds"]["last"] <= g["fds"]["first"] + 2
            and g["threads"]["last"] <= g["threads"]["first"] + 1)
    ok_events = (order["missing"] == 0 and order["reorders"] == 0
                 and order["unique"] >= res["published_events"])
    print(f"verdict: {'FLAT' if flat else 'GROWS'} (RSS bar {args.rss_mb_per_hour} MB/h, "
          f"fds and threads back to their first steady value); no_drop "
          f"{'complete and in order' if ok_events else 'LOST OR REORDERED'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=4.0)
    parser.add_argument("--warmup-s", type=float, default=60.0)
    parser.add_argument("--settle-s", type=float, default=6.0,
                        help="link up this long after each churn step, then a sample")
    parser.add_argument("--steps", help="churn only these steps, by position (0-8, comma-"
                        "separated; 2 = the resets): to tell one kind of churn's cost apart")
    parser.add_argument("--client-log-level", default="INFO")
    parser.add_argument("--rss-mb-per-hour", type=float, default=5.0,
                        help="the verdict's bar for RSS growth")
    parser.add_argument("--domain", type=int, default=60 + os.getpid() % 30)
    parser.add_argument("--json", type=Path, help="also write samples and figures here")
    parser.add_argument("--keep", type=Path, help="work directory to keep (logs)")
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    print(HEADER, flush=True)
    if args.keep:
        args.keep.mkdir(parents=True, exist_ok=True)
        res = asyncio.run(soak(args, args.keep))
    else:
        with tempfile.TemporaryDirectory() as tmp:
            res = asyncio.run(soak(args, Path(tmp)))
    report(res, args)
    if args.json:
        args.json.write_text(json.dumps(res, indent=1, default=str))


if __name__ == "__main__":
    main()
