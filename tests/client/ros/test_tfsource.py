"""The client's TF republisher with real rclpy: /tf throttled, /tf_static latched and whole;
without tf2_msgs, one log line and no TF."""

from __future__ import annotations

import importlib.util
import logging
import math
import time
from typing import Any

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

from fleetctl.client.config import parse_client_config  # noqa: E402
from fleetctl.client.ros.bridge import Bridge  # noqa: E402
from fleetctl.client.ros.runner import status_encoder  # noqa: E402
from fleetctl.wire.codec import Codec  # noqa: E402
from fleetctl.wire.metadata import read_metadata  # noqa: E402
from fleetctl.wire.registry import TypeRegistry  # noqa: E402
from tests.client.ros.test_bridge import FakePort, wait_for  # noqa: E402
from tests.client.ros.test_latched import running_bridge, sent_on  # noqa: E402

pytestmark = pytest.mark.ros
DOMAIN_ID = 34  # this file's own ROS domain (the client tests use 20-39)
HAVE_TF2_MSGS = importlib.util.find_spec("tf2_msgs") is not None
CONFIG = {
    "server_url": "ws://127.0.0.1:1/",
    "robot_name": "r1",
    "publish": [{"topic": "/scan", "type": "sensor_msgs/msg/LaserScan"}],
    "tf": {"translation_delta_m": 0.01, "rotation_delta_rad": 0.01, "max_rate_hz": 10.0},
    "status": {"period_s": 10.0},
}
STATIC_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture(scope="module")
def codec() -> Codec:
    return Codec(TypeRegistry.default())


@pytest.mark.skipif(HAVE_TF2_MSGS, reason="tf2_msgs is installed")
def test_without_tf2_msgs_the_client_logs_once_and_runs(
    ros: tuple[Context, Node], codec: Codec, caplog: pytest.LogCaptureFixture
) -> None:
    context, _peer = ros
    fake = FakePort()
    with caplog.at_level(logging.WARNING, logger="fleetctl.client.ros.tfsource"):
        bridge = Bridge(parse_client_config(CONFIG), codec, codec.registry.typestore,
                        fake.port(), status_encoder(codec, "r1"), context=context)
    try:
        assert bridge.tf is None and len(bridge.inputs) == 1
        lines = [r.getMessage() for r in caplog.records]
        assert len(lines) == 1 and lines[0].startswith("tf: the tf2_msgs package is not "
                                                       "installed: ")
    finally:
        bridge.destroy_node()


def _transform(parent: str, child: str, x: float = 0.0, yaw: float = 0.0) -> Any:
    from geometry_msgs.msg import TransformStamped

    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = parent, child
    t.transform.translation.x = x
    t.transform.rotation.z, t.transform.rotation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    return t


@pytest.mark.skipif(not HAVE_TF2_MSGS, reason="needs tf2_msgs (scripts/ros_msgs.sh)")
def test_static_transforms_published_before_start_arrive_whole_and_latched(
    ros: tuple[Context, Node], codec: Codec
) -> None:
    from tf2_msgs.msg import TFMessage

    context, peer = ros
    # Two static broadcasters, as robot_state_publisher and a camera driver would be.
    for child in ("laser", "camera"):
        pub = peer.create_publisher(TFMessage, "/tf_static", STATIC_QOS)
        pub.publish(TFMessage(transforms=[_transform("base_link", child, x=0.2)]))
    with running_bridge(context, codec, CONFIG) as (bridge, fake):
        assert bridge.tf is not None

        def whole() -> bytes | None:
            frames = sent_on(fake, "/r1/tf_static")
            return frames[-1] if frames and len(codec.decode(frames[-1])[1].transforms) == 2 \
                else None

        frame = wait_for(whole)
        meta, msg = codec.decode(frame)
        assert meta.latched and meta.type == "tf2_msgs/msg/TFMessage"
        assert sorted(t.child_frame_id for t in msg.transforms) == ["camera", "laser"]
        assert bridge.resend_latched() >= 1


@pytest.mark.skipif(not HAVE_TF2_MSGS, reason="needs tf2_msgs (scripts/ros_msgs.sh)")
def test_tf_is_throttled_by_delta_and_rate(ros: tuple[Context, Node], codec: Codec) -> None:
    from tf2_msgs.msg import TFMessage

    context, peer = ros
    with running_bridge(context, codec, CONFIG) as (bridge, fake):
        pub = peer.create_publisher(TFMessage, "/tf", 100)
        wait_for(lambda: pub.get_subscription_count() > 0)
        start = time.monotonic()
        # 100 Hz for 1 s: the base moves 1 cm per message, the wheel never moves.
        for i in range(100):
            pub.publish(TFMessage(transforms=[_transform("odom", "base_link", x=0.01 * i),
                                              _transform("base_link", "wheel")]))
            time.sleep(0.01)  # the publisher's rate, not a synchronization
        elapsed = time.monotonic() - start
        wait_for(lambda: bridge.tf is not None and bridge.tf.stats.transforms_in == 200)
        frames = sent_on(fake, "/r1/tf")
        decoded = [codec.decode(f)[1] for f in frames]
        # The first message is the whole tree, latched for late viewers; within the
        # snapshot period the rest are deltas.
        assert [read_metadata(f).latched for f in frames[:2]] == [True, False]
        assert not any(read_metadata(f).latched for f in frames[1:])
        # At most max_rate_hz messages (plus the first), each with the moved pair only.
        assert 3 <= len(frames) <= elapsed * 10 + 2
        assert sorted(t.child_frame_id for t in decoded[0].transforms) == ["base_link", "wheel"]
        assert all([t.child_frame_id for t in m.transforms] == ["base_link"]
                   for m in decoded[1:])


class RecordingNode:
    """Stands in for the client's node in a unit test of TfRepublisher's callbacks (no
    tf2_msgs needed): records what it creates."""

    def __init__(self) -> None:
        self.subscriptions: dict[str, tuple[Any, QoSProfile]] = {}
        self.timers: list[tuple[float, Any]] = []

    def create_subscription(self, msg_class: Any, topic: str, callback: Any, qos: QoSProfile,
                            *, raw: bool) -> None:
        assert raw
        self.subscriptions[topic] = (callback, qos)

    def create_timer(self, period_s: float, callback: Any, *, clock: Any) -> None:
        from rclpy.clock_type import ClockType

        assert clock.clock_type == ClockType.STEADY_TIME  # not stopped by a wall clock step
        self.timers.append((period_s, callback))


def _tf_cdr(codec: Codec, *transforms: tuple[str, str, float]) -> bytes:
    get = codec.registry.get
    msgs = [get("geometry_msgs/msg/TransformStamped").cls(
        get("std_msgs/msg/Header").cls(get("builtin_interfaces/msg/Time").cls(1, 0), parent),
        child,
        get("geometry_msgs/msg/Transform").cls(get("geometry_msgs/msg/Vector3").cls(x, 0.0, 0.0),
                                               get("geometry_msgs/msg/Quaternion").cls(0, 0, 0, 1)))
        for parent, child, x in transforms]
    tf = get("tf2_msgs/msg/TFMessage").cls(msgs)
    return bytes(codec.registry.typestore.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))


def test_republisher_callbacks_encode_throttled_and_static_frames(codec: Codec) -> None:
    from fleetctl.client.config import TfSpec
    from fleetctl.client.ros.tfsource import TF_STATIC_QOS, TfRepublisher

    node = RecordingNode()
    frames: list[tuple[str, bytes]] = []

    def send(spec: Any, msg: Any, *, latched: bool = False) -> bool:
        frames.append((spec.remote_topic, codec.encode(msg, spec.type, spec.remote_topic,
                                                       latched=latched)))
        return True

    now = [0.0]
    republisher = TfRepublisher(node, TfSpec(max_rate_hz=5.0), "r1",  # type: ignore[arg-type]
                                codec.registry.typestore, send, object, clock_s=lambda: now[0])
    assert set(node.subscriptions) == {"/tf", "/tf_static"}
    assert node.subscriptions["/tf_static"][1] == TF_STATIC_QOS
    assert node.timers[0][0] == pytest.approx(0.2)
    on_tf, _ = node.subscriptions["/tf"]
    on_static, _ = node.subscriptions["/tf_static"]
    on_tf(_tf_cdr(codec, ("odom", "base_link", 0.0), ("base_link", "wheel", 0.0)))
    now[0] = 0.1
    on_tf(_tf_cdr(codec, ("odom", "base_link", 0.5)))  # moved, but too soon
    assert len(frames) == 1
    now[0] = 0.25
    node.timers[0][1]()  # the timer sends what waited
    on_static(_tf_cdr(codec, ("base_link", "laser", 0.2)))
    on_static(_tf_cdr(codec, ("base_link", "laser", 0.2)))  # the same again: nothing
    on_tf(b"\x00\x01garbage")
    topics = [t for t, _ in frames]
    assert topics == ["/r1/tf", "/r1/tf", "/r1/tf_static"]
    second = codec.decode(frames[1][1])[1]
    assert [(t.child_frame_id, t.transform.translation.x) for t in second.transforms] == [
        ("base_link", 0.5)]
    static_meta, static = codec.decode(frames[2][1])
    assert static_meta.latched and [t.child_frame_id for t in static.transforms] == ["laser"]
    assert codec.decode(frames[0][1])[0].latched  # the first is the whole tree
    assert not codec.decode(frames[1][1])[0].latched
    assert republisher.decode_errors == 1 and republisher.stats.static_out == 1
    # A new connection: the next tick sends every pair again, latched (the server may have
    # restarted with nothing), though nothing moved.
    republisher.reconnected()
    now[0] = 0.5
    node.timers[0][1]()
    meta, snapshot = codec.decode(frames[-1][1])
    assert len(frames) == 4 and meta.latched and meta.topic == "/r1/tf"
    assert [t.child_frame_id for t in snapshot.transforms] == ["wheel", "base_link"]


def test_a_subscribe_entry_onto_local_tf_is_refused_with_tf_on(codec: Codec) -> None:
    from fleetctl.errors import ConfigError

    echo = {**CONFIG, "subscribe": [{"remote_topic": "/r2/tf", "type": "tf2_msgs/msg/TFMessage",
                                     "local_topic": "/tf"}]}
    # Refused by the config check now (with fleet.yaml's, before ROS starts); the node's
    # own check stays behind it.
    with pytest.raises(ConfigError, match=r"subscribe\[0\] \(/r2/tf\): local_topic: /tf is "
                                          r"read by the tf section"):
        Bridge(parse_client_config(echo), codec, codec.registry.typestore, FakePort().port(),
               status_encoder(codec, "r1"))
