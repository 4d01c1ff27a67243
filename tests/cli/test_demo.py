"""``fleetctl demo``: the whole fleet starts, both robots come online, and it stops cleanly.

Runs the real command (server, two simulated robots with real rclpy nodes, their clients)
as a child process; a marker in its environment finds any process it leaves behind.
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest

from fleetctl.demo.run import http_json
from fleetctl.waiting import wait_until

pytest.importorskip("rclpy")
pytestmark = [pytest.mark.ros, pytest.mark.slow]
REPO = Path(__file__).resolve().parents[2]
STARTUP_S = 90.0


class Demo:
    """``fleetctl demo ARGS`` with its stdout lines collected by a thread."""

    def __init__(self, args: list[str], tmp_path: Path) -> None:
        self.marker = uuid.uuid4().hex
        env = {**os.environ, "FLEETCTL_TEST_MARKER": self.marker}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "fleetctl.cli.main", "demo", *args,
             "--workdir", str(tmp_path / "demo"), "--port", "0", "--webviz-port", "0"],
            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: queue.Queue[str] = queue.Queue(maxsize=10_000)
        self.output: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.put(line.rstrip("\n"))

    def wait_line(self, pattern: str, timeout_s: float) -> re.Match[str]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.5)
            except queue.Empty:
                if self.process.poll() is not None and self.lines.empty():
                    break
                continue
            self.output.append(line)
            if match := re.search(pattern, line):
                return match
        raise AssertionError(f"no line matching {pattern!r}; output:\n" + "\n".join(self.output))

    def close(self) -> None:
        """Stop the demo if a test failed midway: SIGTERM first (it stops its children),
        SIGKILL only if that fails, then end anything of this demo's that is left."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        for pid in self.leftovers():
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)

    def leftovers(self) -> list[int]:
        """Pids of processes still carrying this demo's environment marker."""
        needle = f"FLEETCTL_TEST_MARKER={self.marker}".encode()
        pids = []
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit() or int(entry.name) == os.getpid():
                continue
            try:
                if needle in (entry / "environ").read_bytes():
                    pids.append(int(entry.name))
            except OSError:
                continue  # exited meanwhile, or not ours to read
        return pids


def _goal_round_trip(port: int, token: str) -> str:
    """As the operator: send robot1 a goal, return the robot's ``/robot1/events`` reply."""
    from websockets.sync.client import connect

    from fleetctl.wire.codec import default_codec
    from fleetctl.wire.control import encode_subscription

    codec = default_codec()
    ts = codec.registry.typestore
    pose_type = "geometry_msgs/msg/PoseStamped"
    goal = ts.types[pose_type](
        header=ts.types["std_msgs/msg/Header"](
            stamp=ts.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="map"),
        pose=ts.types["geometry_msgs/msg/Pose"](
            position=ts.types["geometry_msgs/msg/Point"](x=3.0, y=2.5, z=0.0),
            orientation=ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
    frame = codec.encode(goal, pose_type, "/robot1/goal_pose")
    deadline = time.monotonic() + 30.0
    with connect(f"ws://127.0.0.1:{port}/",
                 additional_headers={"Authorization": f"Bearer {token}"}) as ws:
        ws.send(encode_subscription("/robot1/events", True))
        while time.monotonic() < deadline:
            ws.send(frame)  # resent until the robot's local subscriber has matched
            try:
                reply = ws.recv(timeout=0.5)
            except TimeoutError:
                continue
            if isinstance(reply, bytes):
                meta, msg = codec.decode(reply)
                if meta.topic == "/robot1/events" and "goal received" in msg.data:
                    return str(msg.data)
    raise AssertionError("no 'goal received' event from robot1 within 30 s")


def test_demo_duration_brings_both_robots_online_and_stops_cleanly(tmp_path: Path) -> None:
    demo = Demo(["--duration", "3", "--base-domain-id", "24", "--startup-timeout", "80"],
                tmp_path)
    try:
        port = int(demo.wait_line(r"server\s+ws://127\.0\.0\.1:(\d+)/", STARTUP_S).group(1))
        demo.wait_line(r"all components healthy", STARTUP_S)
        robots = http_json(f"http://127.0.0.1:{port}/robots")
        online = {r["name"] for r in robots["robots"] if r["online"]}
        assert online == {"robot1", "robot2"}
        demo.wait_line(r"stopped ", 60.0)
        assert demo.process.wait(timeout=30) == 0
        wait_until(lambda: not demo.leftovers(), 10.0, describe="no demo process left")
    finally:
        demo.close()
    assert (tmp_path / "demo" / "logs" / "robot1-sim.log").exists()


def test_demo_stops_cleanly_on_sigterm(tmp_path: Path) -> None:
    demo = Demo(["--robots", "1", "--base-domain-id", "27", "--startup-timeout", "80",
                 "--no-webviz"], tmp_path)
    try:
        port = int(demo.wait_line(r"server\s+ws://127\.0\.0\.1:(\d+)/", STARTUP_S).group(1))
        token = demo.wait_line(r"operator token .*:\s+(\S+)$", 5.0).group(1)
        demo.wait_line(r"all components healthy", STARTUP_S)
        # The robot's sensor topics really flow: its battery (sim -> client -> server) shows up.
        wait_until(
            lambda: any(r["name"] == "robot1" and (r.get("battery_level") or -1) > 0
                        for r in (http_json(f"http://127.0.0.1:{port}/robots") or {})
                        .get("robots", [])),
            20.0, describe="robot1's battery level in /robots")
        event = _goal_round_trip(port, token)
        assert "goal received x=3.00 y=2.50" in event
        demo.process.send_signal(signal.SIGTERM)
        assert demo.process.wait(timeout=60) == 0
        wait_until(lambda: not demo.leftovers(), 10.0, describe="no demo process left")
    finally:
        demo.close()


def test_demo_interrupted_during_startup_stops_cleanly(tmp_path: Path) -> None:
    demo = Demo(["--robots", "1", "--base-domain-id", "29", "--no-webviz"], tmp_path)
    try:
        demo.wait_line(r"waiting for robot1 to come online", STARTUP_S)
        demo.process.send_signal(signal.SIGINT)  # what Ctrl-C sends
        assert demo.process.wait(timeout=60) == 0
        demo.wait_line(r"stopped .*server \(0\)", 5.0)
        wait_until(lambda: not demo.leftovers(), 10.0, describe="no demo process left")
    finally:
        demo.close()
