"""The client's TF republisher: local ``/tf`` and ``/tf_static`` to the fleet.

Subscribes the robot's ``/tf`` (best-effort: it matches every broadcaster, and a lost
message is replaced by the next within milliseconds) and ``/tf_static`` (reliable,
TRANSIENT_LOCAL, depth 100: tf2's own static listener QoS, so every static broadcaster's
stored message arrives however late the client starts), both raw. Messages are decoded
with the rosbags type store and go through :mod:`fleetctl.client.tfthrottle`; what comes
out is sent through the bridge like any publish entry's message: ``/<robot>/tf`` (the
throttled pairs, droppable, and now and then a latched snapshot of every pair for late
viewers) and ``/<robot>/tf_static`` (every static pair, latched).

rclpy needs the ``tf2_msgs`` Python package to subscribe; a robot's apt ROS has it, the
PyPI wheels do not (scripts/ros_msgs.sh builds it into a venv). Without it TF is skipped
with one log line and the rest of the client runs.

Callbacks and the timer run on the node's executor thread (one thread), so the throttle
needs no lock.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from fleetctl.client.config import PublishSpec, TfSpec, tf_remote_topics
from fleetctl.client.outagelog import LOG_EVERY, sampled
from fleetctl.client.ros.executor import steady_timer
from fleetctl.client.ros.msgtypes import message_class
from fleetctl.client.tfthrottle import StaticTf, TfStats, TfThrottle
from fleetctl.errors import ConfigError

log = logging.getLogger(__name__)

TF_TYPE = "tf2_msgs/msg/TFMessage"
# What the page needs to place every other message: ahead of scans and clouds, like /pose.
TF_PRIORITY = 5.0
TF_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                    reliability=ReliabilityPolicy.BEST_EFFORT,
                    durability=DurabilityPolicy.VOLATILE)
TF_STATIC_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)

SendMessage = Callable[..., bool]  # Bridge.send_message(spec, msg, *, latched) -> bool


def tf_specs(robot_name: str) -> tuple[PublishSpec, PublishSpec]:
    """The publish entries the republisher sends as: ``/tf`` and ``/tf_static``."""
    tf_topic, static_topic = tf_remote_topics(robot_name)
    return (PublishSpec("/tf", TF_TYPE, TF_PRIORITY, None, False, tf_topic),
            PublishSpec("/tf_static", TF_TYPE, TF_PRIORITY, None, False, static_topic))


class TfRepublisher:
    """Subscriptions, timer and throttle of the TF republisher (see the module docstring).

    Use :func:`start_tf`, which returns None when ``tf2_msgs`` is missing.

    Args:
        node: The client's node.
        spec: Deltas and rate bound.
        robot_name: Names the remote topics.
        typestore: The rosbags type store (decodes CDR, builds the outgoing messages).
        send: The bridge's ``send_message``.
        msg_class: rclpy's ``tf2_msgs.msg.TFMessage``.
        clock_s: Monotonic clock in seconds (injected for tests).
    """

    def __init__(self, node: Node, spec: TfSpec, robot_name: str, typestore: Any,
                 send: SendMessage, msg_class: Any,
                 clock_s: Callable[[], float] = time.monotonic) -> None:
        self.stats = TfStats()
        self.throttle = TfThrottle(spec, self.stats)
        self.static = StaticTf(self.stats)
        self.decode_errors = 0
        self._typestore = typestore
        self._build = typestore.types[TF_TYPE]
        self._send = send
        self._clock_s = clock_s
        self.tf_spec, self.static_spec = tf_specs(robot_name)
        node.create_subscription(msg_class, "/tf", self._on_tf, TF_QOS, raw=True)
        node.create_subscription(msg_class, "/tf_static", self._on_static, TF_STATIC_QOS,
                                 raw=True)
        # A pending change waits at most one period; poll() itself enforces the bound.
        steady_timer(node, self.throttle.period_s, self._tick)

    def _decode(self, cdr: bytes, topic: str) -> list[Any] | None:
        try:
            return list(self._typestore.deserialize_cdr(memoryview(cdr), TF_TYPE).transforms)
        except Exception as exc:  # a bad local message must never stop the node
            self.decode_errors += 1
            if sampled(self.decode_errors):  # not a line per message of a 100 Hz broadcaster
                log.warning("tf: cannot decode a %s message on %s (%d so far; logged first "
                            "and every %dth): %s", TF_TYPE, topic, self.decode_errors,
                            LOG_EVERY, exc)
            return None

    def _on_tf(self, cdr: bytes) -> None:
        transforms = self._decode(cdr, "/tf")
        if transforms is not None:
            self.throttle.offer(transforms)
            self._tick()

    def _tick(self) -> None:
        out = self.throttle.poll(self._clock_s())
        if out is not None:
            # A snapshot is latched: the relay keeps it for whoever subscribes later.
            self._send(self.tf_spec, self._build(transforms=out.transforms),
                       latched=out.snapshot)

    def reconnected(self) -> None:
        """A new connection to the server: send a snapshot soon (it may hold none)."""
        self.throttle.force_snapshot()

    def _on_static(self, cdr: bytes) -> None:
        transforms = self._decode(cdr, "/tf_static")
        if transforms is None:
            return
        out = self.static.offer(transforms)
        if out is not None:
            self._send(self.static_spec, self._build(transforms=out), latched=True)


def start_tf(node: Node, spec: TfSpec, robot_name: str, typestore: Any,
             send: SendMessage) -> TfRepublisher | None:
    """Start the TF republisher, or log one line and return None when ``tf2_msgs`` is not
    installed (the rest of the client runs without TF)."""
    try:
        msg_class = message_class(TF_TYPE)
    except ConfigError as exc:
        log.warning("tf: the tf2_msgs package is not installed: %s; TF is not sent", exc)
        return None
    return TfRepublisher(node, spec, robot_name, typestore, send, msg_class)
