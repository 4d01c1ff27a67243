"""Native ROS 2 DDS consumers for the multi-consumer baseline.

Each consumer is its own process (its own DDS participant), subscribing straight to the
robot's topic across the router, as a ROS user would without a relay::

    python -m fleetctl.e2e.ddssub --topic /points --type sensor_msgs/msg/PointCloud2 \\
        --count 4 --name dds4 --out /e2e/out

DDS discovery is multicast and does not cross the router: the container is started with
``ROS_STATIC_PEERS`` naming the robot (unicast discovery, ROS 2 Jazzy). With ``--count`` > 1
the parent starts the children and forwards SIGTERM. Samples are written like the WebSocket
consumer's; ``topic`` is the robot's wire-style topic (``/robot1/points``) so both compare.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from fleetctl.e2e.payloads import read_stamp
from fleetctl.e2e.profiles import ROBOT
from fleetctl.e2e.samples import Sample, dump


def run_one(topic: str, type_name: str, name: str, out_dir: Path) -> None:
    """One subscriber: record *topic* until SIGTERM/SIGINT."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    from fleetctl.client.ros.msgtypes import message_class
    from fleetctl.client.ros.spin import spin_until_signal
    from fleetctl.wire.registry import TypeRegistry

    ts = TypeRegistry.default().typestore
    wire_topic = f"/{ROBOT}{topic}"
    with (out_dir / f"{name}.jsonl").open("a", buffering=1) as out:

        def on_message(cdr: bytes) -> None:
            now = time.time_ns()
            stamp = read_stamp(ts.deserialize_cdr(cdr, type_name))
            out.write(dump([Sample(wire_topic, stamp.seq, stamp.publish_time_ns, now,
                                   len(cdr), name)]))

        def setup(node: Any) -> None:
            # Reliable, as ROS tools subscribe by default; a shallow history like a viewer.
            qos = QoSProfile(  # type: ignore[no-untyped-call]  # rclpy ships no type hints
                history=HistoryPolicy.KEEP_LAST, depth=5,
                reliability=ReliabilityPolicy.RELIABLE)
            node.create_subscription(message_class(type_name), topic, on_message, qos,
                                     raw=True)
            (out_dir / f"{name}.ready").write_text("ok")

        spin_until_signal(f"e2e_dds_{name.replace('-', '_')}", setup)


def run_many(args: argparse.Namespace) -> int:
    """Start ``--count`` children and wait for them; SIGTERM is forwarded."""
    children = [
        subprocess.Popen([sys.executable, "-m", "fleetctl.e2e.ddssub", "--topic", args.topic,
                          "--type", args.type, "--count", "1", "--name", f"{args.name}-{i}",
                          "--out", str(args.out), "--single"])
        for i in range(args.count)
    ]

    def forward(signum: int, frame: object) -> None:
        for child in children:
            child.send_signal(signal.SIGTERM)

    signal.signal(signal.SIGTERM, forward)
    signal.signal(signal.SIGINT, forward)
    return max(child.wait() for child in children)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point (``python -m fleetctl.e2e.ddssub``)."""
    parser = argparse.ArgumentParser(prog="python -m fleetctl.e2e.ddssub")
    parser.add_argument("--topic", required=True, help="local ROS topic, e.g. /points")
    parser.add_argument("--type", required=True)
    parser.add_argument("--count", type=int, default=1)
    parser.add_argument("--name", default="dds")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--single", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.single:
        run_one(args.topic, args.type, args.name, args.out)
        return 0
    return run_many(args)


if __name__ == "__main__":
    sys.exit(main())
