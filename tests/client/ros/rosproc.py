"""Real rclpy helper processes for the client's integration tests.

Run as ``python -m tests.client.ros.rosproc MODE ...`` with ``ROS_DOMAIN_ID`` set; each prints
JSON lines on stdout that the test reads with deadlines:

- ``listen TOPIC TYPE``: prints ``{"ready": true}`` once a publisher of TOPIC is
  discovered, then ``{"cdr": HEX}`` for every message (raw CDR bytes).
- ``publish TOPIC TYPE CDR RATE_HZ``: waits for a subscriber, prints ``{"ready": true}``,
  then publishes the given CDR bytes at RATE_HZ forever. CDR is hex, or ``@PATH`` of a file
  holding the raw bytes (for messages too large for a command line).
- ``events TOPIC COUNT RATE_HZ``: publishes std_msgs/String ``warmup`` at RATE_HZ
  (reliable) until it gets SIGUSR1, then ``event-1`` ... ``event-COUNT``, printing
  ``{"sent": N}`` every event, then ``{"done": true}`` and keeps running (so late discovery
  loses nothing). The warm-up is there because a publisher that sees a subscriber is not
  yet seen by it: DDS discovery is matched on each side separately, and a volatile reader
  drops what a writer sent before the reader matched it (seen once in CI: the first 32
  events, 0.8 s, lost on a loaded machine). The test sends SIGUSR1 once a warm-up message
  went all the way through.
- ``latch TOPIC TYPE CDR``: publishes CDR once, TRANSIENT_LOCAL depth 1 (as map_server
  does), without waiting for anyone; prints ``{"published": true}`` and keeps running
  (the publisher holds the sample for late subscribers).
- ``status PERIOD_S``: a real client node (:class:`~fleetctl.client.ros.bridge.Bridge` of
  robot ``r1``, status every PERIOD_S) spun by the client's executor; prints
  ``{"status": N}`` for every status frame it hands to its link.
- ``listen-latched TOPIC TYPE``: waits until a TRANSIENT_LOCAL publisher of TOPIC is
  discovered, prints ``{"ready": true}``, and only then subscribes TRANSIENT_LOCAL: every
  ``{"cdr": HEX}`` it prints was published before it subscribed, or after.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from fleetctl.client.ros.msgtypes import message_class

RELIABLE = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE
)
LATCHED = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
_DISCOVERY_TIMEOUT_S = 30.0
WARMUP = "warmup"  # what ``events`` publishes until it is told to start


def _emit(obj: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


def _wait_for_subscriber(node: Node, executor: SingleThreadedExecutor, publisher: Any) -> None:
    deadline = time.monotonic() + _DISCOVERY_TIMEOUT_S
    while publisher.get_subscription_count() == 0:
        if time.monotonic() > deadline:
            raise SystemExit("no subscriber discovered")
        executor.spin_once(timeout_sec=0.05)


def _listen(node: Node, executor: SingleThreadedExecutor, topic: str, type_name: str) -> None:
    node.create_subscription(
        message_class(type_name), topic, lambda cdr: _emit({"cdr": bytes(cdr).hex()}),
        RELIABLE, raw=True,
    )
    deadline = time.monotonic() + _DISCOVERY_TIMEOUT_S
    while node.count_publishers(topic) == 0:
        if time.monotonic() > deadline:
            raise SystemExit(f"no publisher of {topic} discovered")
        executor.spin_once(timeout_sec=0.05)
    _emit({"ready": True})
    executor.spin()


def _publish(node: Node, executor: SingleThreadedExecutor, args: list[str]) -> None:
    topic, type_name, cdr_hex, rate_hz = args
    publisher = node.create_publisher(message_class(type_name), topic, RELIABLE)
    cdr = Path(cdr_hex[1:]).read_bytes() if cdr_hex.startswith("@") else bytes.fromhex(cdr_hex)
    _wait_for_subscriber(node, executor, publisher)
    _emit({"ready": True})
    node.create_timer(1.0 / float(rate_hz), lambda: publisher.publish(cdr))
    executor.spin()


def _latch(node: Node, executor: SingleThreadedExecutor, args: list[str]) -> None:
    topic, type_name, cdr_hex = args
    publisher = node.create_publisher(message_class(type_name), topic, LATCHED)
    cdr = Path(cdr_hex[1:]).read_bytes() if cdr_hex.startswith("@") else bytes.fromhex(cdr_hex)
    publisher.publish(cdr)
    _emit({"published": True})
    executor.spin()


def _listen_latched(node: Node, executor: SingleThreadedExecutor, topic: str,
                    type_name: str) -> None:
    deadline = time.monotonic() + _DISCOVERY_TIMEOUT_S
    while not any(info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                  for info in node.get_publishers_info_by_topic(topic)):
        if time.monotonic() > deadline:
            raise SystemExit(f"no transient-local publisher of {topic} discovered")
        executor.spin_once(timeout_sec=0.05)
    _emit({"ready": True})
    node.create_subscription(
        message_class(type_name), topic, lambda cdr: _emit({"cdr": bytes(cdr).hex()}),
        LATCHED, raw=True,
    )
    executor.spin()


def _events(node: Node, executor: SingleThreadedExecutor, args: list[str]) -> None:
    from std_msgs.msg import String

    topic, count, rate_hz = args[0], int(args[1]), float(args[2])
    publisher = node.create_publisher(String, topic, RELIABLE)
    go = threading.Event()
    signal.signal(signal.SIGUSR1, lambda _signum, _frame: go.set())
    sent = 0

    def tick() -> None:
        nonlocal sent
        if not go.is_set():
            publisher.publish(String(data=WARMUP))
        elif sent < count:
            sent += 1
            publisher.publish(String(data=f"event-{sent}"))
            _emit({"sent": sent})
            if sent == count:
                _emit({"done": True})

    node.create_timer(1.0 / rate_hz, tick)
    executor.spin()


def _status(period_s: str) -> None:
    from fleetctl.client.config import parse_client_config
    from fleetctl.client.ros.bridge import Bridge, LinkPort
    from fleetctl.client.ros.executor import NodeExecutor
    from fleetctl.client.ros.runner import status_encoder
    from fleetctl.wire.codec import Codec
    from fleetctl.wire.registry import TypeRegistry

    sent = 0

    def send_status(frame: bytes) -> None:
        nonlocal sent
        sent += 1
        _emit({"status": sent})

    codec = Codec(TypeRegistry.default())
    config = parse_client_config({"server_url": "ws://127.0.0.1:1/", "robot_name": "r1",
                                  "status": {"period_s": float(period_s)}})
    port = LinkPort(admit=lambda topic: True, send=lambda spec, frame, ns: None,
                    send_status=send_status)
    bridge = Bridge(config, codec, codec.registry.typestore, port, status_encoder(codec, "r1"))
    try:
        NodeExecutor(bridge, bridge.context).spin()
    finally:
        bridge.destroy_node()


def main(argv: list[str]) -> None:
    rclpy.init()
    node = Node("fleetctl_test_helper")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        mode, args = argv[0], argv[1:]
        if mode == "listen":
            _listen(node, executor, args[0], args[1])
        elif mode == "publish":
            _publish(node, executor, args)
        elif mode == "events":
            _events(node, executor, args)
        elif mode == "latch":
            _latch(node, executor, args)
        elif mode == "status":
            _status(args[0])
        elif mode == "listen-latched":
            _listen_latched(node, executor, args[0], args[1])
        else:
            raise SystemExit(f"unknown mode {mode!r}")
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.utilities.try_shutdown()


if __name__ == "__main__":
    main(sys.argv[1:])
