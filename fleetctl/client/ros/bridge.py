"""The robot client's ROS 2 side: local topics in, fleet frames out, and back.

:class:`Bridge` is an rclpy node. For every ``publish`` entry of the client config it holds a
*raw* subscription (CDR bytes, no Python message object is ever built by rclpy) whose
reliability follows the topic's publishers (:mod:`fleetctl.client.ros.qos`) and, in the
callback, asks the link whether the topic is due (Robofleet Algorithm 1's rate limit) before
doing any work, then converts CDR -> rosbags message -> FlatBuffer frame, compresses it when
the entry asks for it (:mod:`fleetctl.wire.compression`; the link fragments afterwards) and
hands the frame to the link. For every ``subscribe`` entry it holds a publisher; frames from
the link (reassembled and decompressed by the link) are decoded, serialized to CDR and
published as bytes.

The node knows nothing about WebSockets: it talks to the link through two callables
(:class:`LinkPort`) so it is tested without a server, and the link is tested without ROS.
Callbacks run on the rclpy executor thread, except those of uncompressed ``publish`` topics
when the node is given a :class:`~fleetctl.client.ros.intake.LoopIntake` (then on the asyncio
thread); :meth:`Bridge.deliver` is called from the asyncio thread (rclpy publishers may be
used from any thread).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import re2
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

from fleetctl.client.config import ClientConfig, PublishSpec, SubscribeSpec
from fleetctl.client.ros import qos
from fleetctl.client.ros.intake import LoopIntake
from fleetctl.client.ros.msgtypes import message_class
from fleetctl.client.ros.qos import AdaptiveSubscription
from fleetctl.errors import ConfigError
from fleetctl.wire.compression import CompressionCodec, compress

log = logging.getLogger(__name__)

# Commands republished locally (goal poses): reliable, like RViz's tools publish them.
COMMAND_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
QOS_REFRESH_PERIOD_S = 1.0  # how often local subscriptions re-check their publishers' QoS
MAX_DYNAMIC_PUBLISHERS = 64  # regex subscriptions without local_topic: one publisher per topic


@dataclass(frozen=True)
class LinkPort:
    """What the node needs from the link.

    Attributes:
        admit: ``admit(remote_topic) -> bool``: False when the topic's rate limit says skip
            this message (checked before any decoding work).
        send: ``send(spec, frame)``: queue an encoded frame of publish entry *spec*
            (thread-safe; called from the rclpy executor's thread or the loop's).
        send_status: ``send_status(frame)``: queue an encoded RobofleetStatus frame.
    """

    admit: Callable[[str], bool]
    send: Callable[[PublishSpec, bytes], None]
    send_status: Callable[[bytes], None]


@dataclass
class BridgeStats:
    """Counters of the node (read from any thread; each is a plain int).

    Attributes:
        local_in: raw messages received from local topics.
        rate_limited: of those, skipped because the link said not yet.
        sent: frames handed to the link.
        compressed: of those, sent as a Compressed frame.
        compression_skipped: of those, sent plain on a compressed topic because
            compression would not have saved 5 % (incompressible data).
        encode_errors: local messages that could not be encoded or compressed (logged).
        frames_in: frames received from the link.
        published_local: of those, published on a local topic.
        decode_errors: frames that could not be decoded or serialized (logged).
        type_mismatch: frames whose type differs from the subscribe entry's (dropped).
        unmatched: frames matching no subscribe entry (dropped).
        publishers_over_limit: frames dropped because a regex entry already has
            :data:`MAX_DYNAMIC_PUBLISHERS` local topics.
        status_sent: RobofleetStatus frames sent.
    """

    local_in: int = 0
    rate_limited: int = 0
    sent: int = 0
    compressed: int = 0
    compression_skipped: int = 0
    encode_errors: int = 0
    frames_in: int = 0
    published_local: int = 0
    decode_errors: int = 0
    type_mismatch: int = 0
    unmatched: int = 0
    publishers_over_limit: int = 0
    status_sent: int = 0
    per_topic_sent: dict[str, int] = field(default_factory=dict)


def _entry_class(where: str, type_name: str) -> Any:
    """The message class of a config entry; fails at start (not on the first message).

    Raises:
        ConfigError: naming the entry, when the type's package is not installed.
    """
    try:
        return message_class(type_name)
    except ConfigError as exc:
        raise ConfigError(f"{where}: type: {exc}") from exc


class _Route:
    """One subscribe entry: its matcher and its local publisher(s)."""

    def __init__(self, node: Node, spec: SubscribeSpec) -> None:
        self.spec = spec
        self._node = node
        self._cls = message_class(spec.type)
        self._regex = re2.compile(spec.remote_topic) if spec.is_regex else None
        self._publishers: dict[str, Any] = {}
        if spec.local_topic is not None:
            self._publishers[spec.local_topic] = node.create_publisher(
                self._cls, spec.local_topic, COMMAND_QOS
            )

    def matches(self, topic: str) -> bool:
        if self._regex is None:
            return topic == self.spec.remote_topic
        return self._regex.fullmatch(topic) is not None

    def publisher_for(self, topic: str) -> Any | None:
        """The publisher for remote *topic*; None when the dynamic bound is reached."""
        local = self.spec.local_topic or topic
        publisher = self._publishers.get(local)
        if publisher is None:
            if len(self._publishers) >= MAX_DYNAMIC_PUBLISHERS:
                return None
            publisher = self._node.create_publisher(self._cls, local, COMMAND_QOS)
            self._publishers[local] = publisher
        return publisher


def _check_no_echo(config: ClientConfig) -> None:
    """Refuse a subscribe entry republishing onto a topic the client also sends.

    The node would pick up its own republished messages and send them again, forever.

    Raises:
        ConfigError: naming both entries.
    """
    sent = {spec.topic: i for i, spec in enumerate(config.publish)}
    for j, sub in enumerate(config.subscribe):
        if sub.local_topic is not None and sub.local_topic in sent:
            raise ConfigError(
                f"subscribe[{j}] ({sub.remote_topic}): local_topic: {sub.local_topic} is also "
                f"sent by publish[{sent[sub.local_topic]}]: the client would echo it forever"
            )


class Bridge(Node):
    """The client's rclpy node (see the module docstring).

    Args:
        config: the validated client config.
        codec: a :class:`fleetctl.wire.codec.Codec` (``encode``/``decode``).
        typestore: the rosbags type store of the codec's registry (CDR conversions).
        port: the link's side of the bridge.
        encode_status: ``encode_status(battery_level) -> bytes`` building this robot's
            RobofleetStatus frame; battery is a fraction in [0, 1] or None when unknown.
        clock_ns: wall clock in ns since the epoch (injected for tests).
        context: the rclpy context of the node (None: the global one).
        intake: takes the uncompressed ``publish`` topics' messages in the asyncio loop's
            thread (None: the executor does).
    """

    def __init__(
        self,
        config: ClientConfig,
        codec: Any,
        typestore: Any,
        port: LinkPort,
        encode_status: Callable[[float | None], bytes],
        clock_ns: Callable[[], int] = time.time_ns,
        context: Any = None,
        intake: LoopIntake | None = None,
    ) -> None:
        _check_no_echo(config)
        # No services: the node's settings come from the client's YAML file, and its
        # executor (fleetctl.client.ros.executor) serves topics and timers only.
        super().__init__(
            f"fleetctl_client_{config.robot_name}", context=context,
            start_parameter_services=False,
            parameter_overrides=[Parameter("start_type_description_service", value=False)])
        self.stats = BridgeStats()
        self._config = config
        self._codec = codec
        self._typestore = typestore
        self._port = port
        self._encode_status = encode_status
        self._clock_ns = clock_ns
        self._seq: dict[str, int] = {}
        self._seq_lock = threading.Lock()  # callbacks run on the executor's and the loop's thread
        self._battery: float | None = None
        self.inputs: list[AdaptiveSubscription] = []
        for i, spec in enumerate(config.publish):
            cls = _entry_class(f"publish[{i}] ({spec.topic})", spec.type)
            self.inputs.append(AdaptiveSubscription(
                self, cls, spec.topic, self._make_callback(spec), no_drop=spec.no_drop,
                # A compressed topic's zstd/deflate work (milliseconds per megabyte, with
                # the GIL released) stays off the loop, which other topics' frames wait on.
                intake=intake if spec.compression == "none" else None))
        self.create_timer(QOS_REFRESH_PERIOD_S, self._refresh_qos)
        self._routes: list[_Route] = []
        for i, sub in enumerate(config.subscribe):
            _entry_class(f"subscribe[{i}] ({sub.remote_topic})", sub.type)
            self._routes.append(_Route(self, sub))
        if config.status.battery_topic is not None:
            from sensor_msgs.msg import BatteryState

            self.create_subscription(
                BatteryState, config.status.battery_topic, self._on_battery,
                qos.profile(reliable=False, no_drop=False),
            )
        self.create_timer(config.status.period_s, self.send_status)

    # --- local -> fleet -----------------------------------------------------------------

    def _refresh_qos(self) -> None:
        for subscription in self.inputs:
            subscription.refresh()

    def _make_callback(self, spec: PublishSpec) -> Callable[[bytes], None]:
        def callback(cdr: bytes) -> None:
            self.on_local_message(spec, cdr)

        return callback

    def on_local_message(self, spec: PublishSpec, cdr: bytes) -> None:
        """Encode one local CDR message of *spec* and hand it to the link (unless rate limited)."""
        self.stats.local_in += 1
        if not self._port.admit(spec.remote_topic):
            self.stats.rate_limited += 1
            return
        try:
            # A view: rosbags slices off the CDR header, which copies a bytes object
            # (1 MB per cloud) but not a view; arrays then reference rclpy's buffer.
            msg = self._typestore.deserialize_cdr(memoryview(cdr), spec.type)
            # A view, not a copy: the link only reads it (fragments are new buffers).
            frame = self._codec.encode_view(
                msg,
                spec.type,
                spec.remote_topic,
                no_drop=spec.no_drop,
                publish_time_ns=self._clock_ns(),
                seq=self._next_seq(spec.remote_topic),
            )
            if spec.compression != "none":
                frame = self._compress(spec, frame)
        except Exception as exc:  # a bad local message must never stop the node
            self.stats.encode_errors += 1
            log.warning("cannot encode %s from %s: %s", spec.type, spec.topic, exc)
            return
        self._port.send(spec, frame)
        self.stats.sent += 1
        self.stats.per_topic_sent[spec.remote_topic] = (
            self.stats.per_topic_sent.get(spec.remote_topic, 0) + 1
        )

    def _compress(self, spec: PublishSpec, frame: bytes) -> bytes:
        """Before the link fragments it: receivers reassemble, then decompress."""
        out = compress(frame, codec=CompressionCodec.from_name(spec.compression),
                       topic=spec.remote_topic, no_drop=spec.no_drop, frame_codec=self._codec)
        if out is frame:
            self.stats.compression_skipped += 1
        else:
            self.stats.compressed += 1
        return out

    def _next_seq(self, topic: str) -> int:
        # Sequence numbers start at the wall clock in microseconds, so a restarted client's
        # numbers are above its previous run's and receivers' duplicate filters (which drop
        # a no_drop seq not above the last one seen) do not eat its first messages.
        with self._seq_lock:
            seq = self._seq.get(topic, self._clock_ns() // 1000) + 1
            self._seq[topic] = seq
            return seq

    # --- status ----------------------------------------------------------------------------

    def _on_battery(self, msg: Any) -> None:
        percentage = float(msg.percentage)
        # BatteryState uses NaN for "unknown"; keep the last known value in that case.
        if percentage == percentage:
            self._battery = min(max(percentage, 0.0), 1.0)

    def send_status(self) -> None:
        """Send one RobofleetStatus (battery from the configured topic, if any)."""
        try:
            frame = self._encode_status(self._battery)
        except Exception as exc:
            self.stats.encode_errors += 1
            log.warning("cannot encode status: %s", exc)
            return
        self._port.send_status(frame)
        self.stats.status_sent += 1

    # --- fleet -> local -----------------------------------------------------------------

    def deliver(self, frame: bytes) -> None:
        """Publish one frame from the fleet on the local topic of its subscribe entry.

        Never raises: undecodable frames, type mismatches and frames no entry wants are
        counted and logged.
        """
        self.stats.frames_in += 1
        try:
            meta, msg = self._codec.decode(frame)
        except Exception as exc:
            self.stats.decode_errors += 1
            log.warning("dropping undecodable frame from the server: %s", exc)
            return
        route = next((r for r in self._routes if r.matches(meta.topic)), None)
        if route is None:
            self.stats.unmatched += 1
            return
        if meta.type != route.spec.type:
            self.stats.type_mismatch += 1
            log.warning(
                "dropping %s on %s: subscribe entry expects %s",
                meta.type,
                meta.topic,
                route.spec.type,
            )
            return
        publisher = route.publisher_for(meta.topic)
        if publisher is None:
            self.stats.publishers_over_limit += 1
            return
        try:
            cdr = self._typestore.serialize_cdr(msg, meta.type)
        except Exception as exc:
            self.stats.decode_errors += 1
            log.warning("cannot serialize %s from %s: %s", meta.type, meta.topic, exc)
            return
        publisher.publish(bytes(cdr))
        self.stats.published_local += 1

