"""Whole-process cost of ``fleetctl client`` for a 10 Hz 1 MB PointCloud2 (issue 3, section 4).

Usage::

    .venv/bin/python benchmarks/client_process.py [--seconds 20] [--rounds 3] [--warmup 5]

``benchmarks/client_link.py`` (c) measures the client's own per-message path in-process;
this measures what an operator sees in ``top``: the real ``fleetctl client`` process (rclpy
node, raw-CDR subscription, encode, fragments, WebSocket) fed by a separate rclpy publisher
process over DDS, relaying to a fleetctl relay with one consumer, side by side in the same
run with a bare rclpy raw subscriber process (the floor any rclpy-based client pays for
receiving 10 MB/s from DDS; Robofleet's Table II also excludes "native ROS"). The bare
subscriber raises glibc's malloc thresholds as the client does for itself
(``fleetctl.client.memory``), so the two differ by the client's own work only. It gets the
same cloud on a topic of its own, published 50 ms after the client's, so that the two do
not compete for the machine's two cores at the same instants.

CPU = the time each thread ran, from ``/proc/PID/task/TID/schedstat`` (nanoseconds; ``stat``'s
clock ticks are too coarse), summed over the process, over each measuring window, as a
share of one core, for ``--rounds`` consecutive windows of the same processes (the
machine's speed drifts; the median is the figure); the client's share is also split by
thread (the asyncio thread is the main one, the rclpy executor the other ``fleetctl``
thread, Fast DDS's are named ``dds.*``). Memory = ``VmRSS`` at the end. The consumer's frame
count proves the stream flowed (the run stops with an error when it does not).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
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
BARE_TOPIC = "/points_bare"
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
topics = {topics!r}
pubs = [node.create_publisher(message_class("{type}"), t, qos) for t in topics]
msg = point_cloud(registry)
turn = 0
def tick():
    global turn
    now = time.time_ns()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(now, 10**9)
    pubs[turn].publish(bytes(store.serialize_cdr(msg, "{type}")))
    turn = (turn + 1) % len(pubs)
node.create_timer(0.1 / len(pubs), tick)
print("ready", flush=True)
rclpy.spin(node)
"""

BARE_SUBSCRIBER = """
from fleetctl.client.memory import tune_malloc
tune_malloc()
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


def thread_seconds(pid: int, tid: str) -> float:
    """Time thread *tid* of *pid* ran on a CPU, in seconds.

    ``schedstat``'s first field is the scheduler's own count in nanoseconds; ``stat``'s
    utime + stime come in clock ticks (10 ms), 0.05 % of a core over a 20 s window, too
    coarse to tell changes of a tenth of a percent apart.
    """
    return int(Path(f"/proc/{pid}/task/{tid}/schedstat").read_text().split()[0]) / 1e9


def thread_cpu_seconds(pid: int) -> dict[str, float]:
    """CPU seconds per thread of *pid*, keyed ``asyncio``, ``rclpy executor`` or ``DDS``."""
    out: dict[str, float] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            seconds = thread_seconds(pid, task.name)
        except OSError:  # the thread ended between listing and reading
            continue
        if int(task.name) == pid:
            key = "asyncio"
        elif name.startswith("dds.") or name.startswith("ros2") or name != "fleetctl":
            key = "DDS"
        else:
            key = "rclpy executor"
        out[key] = out.get(key, 0.0) + seconds
    return out


def cpu_seconds(pid: int) -> float:
    """CPU seconds of all live threads of *pid* (the processes measured keep theirs)."""
    return sum(thread_cpu_seconds(pid).values())


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


def window(procs: dict[str, subprocess.Popen[str]], seconds: float,
           peer: Peer) -> dict[str, Any]:
    """One measuring window: CPU % of each process and of the client's threads."""
    client_pid = procs["fleetctl client"].pid
    peer.cmd("reset")
    before = {name: cpu_seconds(p.pid) for name, p in procs.items()}
    threads_before = thread_cpu_seconds(client_pid)
    t0 = time.monotonic()
    time.sleep(seconds)  # the measuring window itself
    elapsed = time.monotonic() - t0
    after = {name: cpu_seconds(p.pid) for name, p in procs.items()}
    threads_after = thread_cpu_seconds(client_pid)
    frames = peer.cmd("report").get(REMOTE, {}).get("frames", 0)
    return {
        "cpu_pct": {name: 100 * (after[name] - before[name]) / elapsed for name in procs},
        "client_threads_pct": {k: 100 * (v - threads_before.get(k, 0.0)) / elapsed
                               for k, v in threads_after.items()},
        "frames": frames, "seconds": elapsed,
    }


def run(seconds: float, rounds: int, warmup: float, work: Path) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(HERE.parent),
           "ROS_DOMAIN_ID": str(100 + os.getpid() % 100),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
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
        procs.append(client)
        bare = start([PY, "-c", BARE_SUBSCRIBER.format(type=TYPE, topic=BARE_TOPIC)], env,
                     work / "bare.log")
        procs.append(bare)
        publisher = start([PY, "-c", PUBLISHER.format(type=TYPE, topics=[TOPIC, BARE_TOPIC])],
                          env, work / "publisher.log")
        procs.append(publisher)
        wait_ready(bare, "bare subscriber")
        wait_ready(publisher, "publisher")
        if peer.wait_frames(REMOTE, 10, 60.0).get("frames", 0) < 10:
            raise SystemExit(f"no stream on {REMOTE} within 60 s: see {work / 'client.log'}")
        time.sleep(warmup)  # steady state: measuring windows start after the warm-up
        measured = {"fleetctl client": client, "bare rclpy subscriber": bare}
        windows = [window(measured, seconds, peer) for _ in range(rounds)]
        return {"windows": windows, "rss_mb": {name: rss_mb(p.pid)
                                               for name, p in measured.items()}}
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
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--warmup", type=float, default=5.0)
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args()
    # The child processes run in sessions of their own (so a terminal's Ctrl-C reaches
    # them only through this script): on SIGTERM too, unwind so run()'s cleanup stops them.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    with tempfile.TemporaryDirectory() as tmp:
        res = run(args.seconds, args.rounds, args.warmup, Path(tmp))
    windows = res["windows"]
    print(f"10 Hz PointCloud2 of 1 MiB over DDS, {args.rounds} windows of {args.seconds:.0f} s "
          f"after {args.warmup:.0f} s warm-up; frames delivered per window: "
          f"{', '.join(str(w['frames']) for w in windows)}")
    print(f"    {'process':28s} {'CPU % of one core: median (windows)':>40s} {'RSS MB':>8s}")
    medians = {}
    for name in ("fleetctl client", "bare rclpy subscriber"):
        values = [w["cpu_pct"][name] for w in windows]
        medians[name] = statistics.median(values)
        spread = ", ".join(f"{v:.2f}" for v in values)
        print(f"    {name:28s} {medians[name]:14.2f} ({spread})".ljust(74)
              + f"{res['rss_mb'][name]:8.1f}")
    for key in ("rclpy executor", "asyncio", "DDS"):
        values = [w["client_threads_pct"].get(key, 0.0) for w in windows]
        print(f"      client thread: {key:16s} {statistics.median(values):6.2f}")
    extra = medians["fleetctl client"] - medians["bare rclpy subscriber"]
    print(f"    client cost above the bare subscriber: {extra:.2f} % "
          f"(bar: whole client < 3 %: {'met' if medians['fleetctl client'] < 3 else 'NOT met'})")
    if args.json:
        args.json.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
