"""Whole-process cost of ``fleetctl client`` for a 10 Hz 1 MB PointCloud2 (issue 3, section 4).

Usage::

    .venv/bin/python benchmarks/client_process.py [--seconds 20] [--warmup 5]

``benchmarks/client_link.py`` (c) measures the client's own per-message path in-process;
this measures what an operator sees in ``top``: the real ``fleetctl client`` process (rclpy
node, raw-CDR subscription, encode, fragments, WebSocket) fed by a separate rclpy publisher
process over DDS, relaying to a fleetctl relay with one consumer, side by side in the same
run with a bare rclpy raw subscriber process on the same topic (the floor any rclpy-based
client pays for receiving 10 MB/s from DDS; Robofleet's Table II also excludes "native
ROS"). CPU = utime + stime from ``/proc/PID/stat`` over the measuring window, as a share of
one core; memory = ``VmRSS`` at the end. The consumer's count proves the stream flowed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from client_link import ROBOT_TOKEN, Peer, write_auth  # noqa: E402

PY = sys.executable
TOPIC = "/points"
REMOTE = "/bench/points"
TYPE = "sensor_msgs/msg/PointCloud2"

PUBLISHER = """
import sys, time, rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy
from fleetctl.client.ros.msgtypes import message_class
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.samples import point_cloud
registry = TypeRegistry.default()
store = registry.typestore
rclpy.init()
node = rclpy.create_node("bench_cloud_publisher")
qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE)
pub = node.create_publisher(message_class("{type}"), "{topic}", qos)
msg = point_cloud(registry)
def tick():
    now = time.time_ns()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(now, 10**9)
    pub.publish(bytes(store.serialize_cdr(msg, "{type}")))
node.create_timer(0.1, tick)
print("ready", flush=True)
rclpy.spin(node)
"""

BARE_SUBSCRIBER = """
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy
from fleetctl.client.ros.msgtypes import message_class
rclpy.init()
node = rclpy.create_node("bench_bare_subscriber")
count = 0
def cb(raw):
    global count
    count += 1
qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE)
node.create_subscription(message_class("{type}"), "{topic}", cb, qos, raw=True)
print("ready", flush=True)
rclpy.spin(node)
"""


def cpu_seconds(pid: int) -> float:
    """utime + stime of *pid* in seconds (fields 14 and 15 of /proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def start(argv: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=log.open("w"),
                            text=True, start_new_session=True)


def wait_ready(proc: subprocess.Popen[str], what: str) -> None:
    assert proc.stdout is not None
    line = proc.stdout.readline()  # blocks until the child prints "ready" or exits
    if not line.startswith("ready"):
        raise SystemExit(f"{what} failed to start (exit {proc.poll()})")


def run(seconds: float, warmup: float, work: Path) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(HERE.parent),
           "ROS_DOMAIN_ID": str(100 + os.getpid() % 100), "ROS_LOCALHOST_ONLY": "1"}
    peer = Peer([], "127.0.0.1", write_auth(work))
    procs: list[subprocess.Popen[str]] = []
    try:
        token = work / "token"
        token.write_text(ROBOT_TOKEN)
        config = work / "client.yaml"
        config.write_text(json.dumps({
            "server_url": peer.url, "robot_name": "bench", "token_file": str(token),
            "publish": [{"topic": TOPIC, "type": TYPE, "remote_topic": REMOTE}],
        }))
        client = start([str(Path(PY).parent / "fleetctl"), "client", "--config", str(config)], env,
                       work / "client.log")
        bare = start([PY, "-c", BARE_SUBSCRIBER.format(type=TYPE, topic=TOPIC)], env,
                     work / "bare.log")
        publisher = start([PY, "-c", PUBLISHER.format(type=TYPE, topic=TOPIC)], env,
                          work / "publisher.log")
        procs += [client, bare, publisher]
        wait_ready(bare, "bare subscriber")
        wait_ready(publisher, "publisher")
        peer.wait_frames(REMOTE, 10, 60.0)  # the stream flows end to end
        time.sleep(warmup)  # steady state: measuring window starts after the warm-up
        peer.cmd("reset")
        before = {p.pid: cpu_seconds(p.pid) for p in (client, bare)}
        t0 = time.monotonic()
        time.sleep(seconds)  # the measuring window itself
        elapsed = time.monotonic() - t0
        after = {p.pid: cpu_seconds(p.pid) for p in (client, bare)}
        report = peer.cmd("report").get(REMOTE, {})
        out = {name: {"cpu_pct": 100 * (after[p.pid] - before[p.pid]) / elapsed,
                      "rss_mb": rss_mb(p.pid)}
               for name, p in (("fleetctl client", client), ("bare rclpy subscriber", bare))}
        out["delivered"] = {"frames": report.get("frames", 0), "seconds": elapsed}
        return out
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
        peer.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--warmup", type=float, default=5.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        res = run(args.seconds, args.warmup, Path(tmp))
    print(f"10 Hz PointCloud2 of 1 MiB over DDS, {args.seconds:.0f} s after "
          f"{args.warmup:.0f} s warm-up; delivered {res['delivered']['frames']} frames")
    print(f"    {'process':28s} {'CPU % of one core':>18s} {'RSS MB':>8s}")
    for name in ("fleetctl client", "bare rclpy subscriber"):
        print(f"    {name:28s} {res[name]['cpu_pct']:18.2f} {res[name]['rss_mb']:8.1f}")
    extra = res["fleetctl client"]["cpu_pct"] - res["bare rclpy subscriber"]["cpu_pct"]
    print(f"    client cost above the bare subscriber: {extra:.2f} % (bar: whole client < 3 %)")


if __name__ == "__main__":
    main()
