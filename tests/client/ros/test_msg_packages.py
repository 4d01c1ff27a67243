"""The message packages scripts/ros_msgs.sh builds: real rclpy across two processes.

Each direction crosses a process boundary through Fast DDS, and each side's bytes are
checked against rosbags' CDR serializer (an independent implementation):

- this process publishes typed messages (Python -> C -> CDR through the built libraries), a
  ``rosproc listen`` child receives the raw CDR, rosbags decodes it;
- a ``rosproc publish`` child publishes CDR that rosbags encoded, this process subscribes
  typed (CDR -> C -> Python) and reads the fields.

The RIHS01 type hash the child advertises over discovery must be the one a real Jazzy
``ros2 topic info -v /tf`` shows, so these packages interoperate with apt-installed ones.
Skipped where the packages are not installed (run ``scripts/ros_msgs.sh .venv``).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("tf2_msgs.msg", reason="tf2_msgs not built: run scripts/ros_msgs.sh")
pytest.importorskip("foxglove_msgs.msg", reason="foxglove_msgs not built: run scripts/ros_msgs.sh")

from builtin_interfaces.msg import Time
from foxglove_msgs.msg import CompressedVideo
from geometry_msgs.msg import TransformStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from tf2_msgs.msg import TFMessage

from tests.client.ros.harness import REPO, JsonProc, ros_helper
from tests.support import wait_for_value

pytestmark = pytest.mark.ros
DOMAIN_ID = 35  # this file's own ROS domain (the client tests use 20-39)
TF = "tf2_msgs/msg/TFMessage"
VIDEO = "foxglove_msgs/msg/CompressedVideo"
# What Jazzy's apt tf2_msgs advertises (``ros2 topic info -v /tf``, also rosbags' value).
TF_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
RELIABLE = QoSProfile(  # type: ignore[no-untyped-call]
    depth=100, reliability=ReliabilityPolicy.RELIABLE)
DEADLINE_S = 30.0


@pytest.fixture(scope="module")
def typestore() -> Any:
    """rosbags' Jazzy type store, taught CompressedVideo from fleetctl's definition."""
    store = get_typestore(Stores.ROS2_JAZZY)
    text = (REPO / "fleetctl/wire/msg/foxglove_msgs/msg/CompressedVideo.msg").read_text()
    store.register(get_types_from_msg(text, VIDEO))
    return store


@pytest.fixture
def children(tmp_path: Path) -> Iterator[list[JsonProc]]:
    """Helper processes started by a test, stopped after it."""
    procs: list[JsonProc] = []
    yield procs
    for proc in procs:
        proc.stop()


def _transform(parent: str, child: str, x: float, sec: int) -> TransformStamped:
    msg = TransformStamped(child_frame_id=child)
    msg.header.frame_id = parent
    msg.header.stamp = Time(sec=sec, nanosec=5)
    msg.transform.translation.x = x
    msg.transform.rotation.z = 0.6
    msg.transform.rotation.w = 0.8
    return msg


def _publish_until_heard(ros: tuple[Any, Any], cls: type, topic: str, msg: Any,
                         child: JsonProc) -> bytes:
    """Publish *msg* typed every 50 ms (a timer of the peer node) until *child* prints it."""
    _context, peer = ros
    publisher = peer.create_publisher(cls, topic, RELIABLE)
    timer = peer.create_timer(0.05, lambda: publisher.publish(msg))
    try:
        line = child.wait_for(lambda d: "cdr" in d, DEADLINE_S, f"a {cls.__name__} on {topic}")
    finally:
        peer.destroy_timer(timer)
    return bytes.fromhex(line["cdr"])


def _receive_typed(ros: tuple[Any, Any], cls: type, topic: str) -> Any:
    """Subscribe *cls* on *topic* and return the first message received."""
    _context, peer = ros
    got: list[Any] = []
    lock = threading.Lock()

    def on_message(msg: Any) -> None:
        with lock:
            got.append(msg)

    peer.create_subscription(cls, topic, on_message, RELIABLE)
    return wait_for_value(lambda: got[:1], DEADLINE_S)[0]


def test_tfmessage_typed_publisher_to_another_process(
    ros: tuple[Any, Any], children: list[JsonProc], tmp_path: Path, typestore: Any
) -> None:
    child = ros_helper("listen", ["/tf_pkgtest", TF], DOMAIN_ID, tmp_path / "listen.log")
    children.append(child)
    msg = TFMessage(transforms=[_transform("odom", "base_link", 1.25, 7),
                                _transform("base_link", "laser", -0.5, 8)])

    cdr = _publish_until_heard(ros, TFMessage, "/tf_pkgtest", msg, child)

    decoded = typestore.deserialize_cdr(cdr, TF)
    assert [(t.header.frame_id, t.child_frame_id) for t in decoded.transforms] == [
        ("odom", "base_link"), ("base_link", "laser")]
    assert decoded.transforms[0].transform.translation.x == 1.25
    assert decoded.transforms[1].header.stamp.sec == 8
    assert decoded.transforms[1].transform.rotation.w == 0.8


def test_tfmessage_from_another_process_with_jazzy_type_hash(
    ros: tuple[Any, Any], children: list[JsonProc], tmp_path: Path, typestore: Any
) -> None:
    ts = typestore.types
    stamp = ts["builtin_interfaces/msg/Time"](sec=3, nanosec=9)
    header = ts["std_msgs/msg/Header"](stamp=stamp, frame_id="map")
    transform = ts["geometry_msgs/msg/Transform"](
        translation=ts["geometry_msgs/msg/Vector3"](x=2.0, y=-1.0, z=0.25),
        rotation=ts["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    reference = ts[TF](transforms=[
        ts["geometry_msgs/msg/TransformStamped"](header=header, child_frame_id="odom",
                                                  transform=transform)])
    cdr = typestore.serialize_cdr(reference, TF)
    child = ros_helper("publish", ["/tf_pkgtest_in", TF, cdr.hex(), "20"], DOMAIN_ID,
                       tmp_path / "publish.log")
    children.append(child)

    got = _receive_typed(ros, TFMessage, "/tf_pkgtest_in")

    assert isinstance(got, TFMessage)
    (only,) = got.transforms
    assert (only.header.frame_id, only.child_frame_id) == ("map", "odom")
    assert (only.header.stamp.sec, only.header.stamp.nanosec) == (3, 9)
    assert (only.transform.translation.y, only.transform.translation.z) == (-1.0, 0.25)
    _context, peer = ros
    infos = peer.get_publishers_info_by_topic("/tf_pkgtest_in")
    assert [str(info.topic_type_hash) for info in infos] == [TF_HASH]
    assert typestore.hash_rihs01(TF) == TF_HASH


def test_compressed_video_both_ways(
    ros: tuple[Any, Any], children: list[JsonProc], tmp_path: Path, typestore: Any
) -> None:
    payload = bytes(range(256)) * 40  # 10 KiB, every byte value, as an access unit is
    listen = ros_helper("listen", ["/video_pkgtest", VIDEO], DOMAIN_ID, tmp_path / "l.log")
    children.append(listen)
    sent = CompressedVideo(timestamp=Time(sec=11, nanosec=12), frame_id="camera",
                           data=payload, format="h264")

    cdr = _publish_until_heard(ros, CompressedVideo, "/video_pkgtest", sent, listen)

    decoded = typestore.deserialize_cdr(cdr, VIDEO)
    assert (decoded.frame_id, decoded.format, decoded.timestamp.sec) == ("camera", "h264", 11)
    assert decoded.data.tobytes() == payload

    reference = typestore.types[VIDEO](
        timestamp=typestore.types["builtin_interfaces/msg/Time"](sec=4, nanosec=0),
        frame_id="front", data=decoded.data[::-1].copy(), format="av1")
    publish = ros_helper(
        "publish", ["/video_pkgtest_in", VIDEO, typestore.serialize_cdr(reference, VIDEO).hex(),
                    "20"], DOMAIN_ID, tmp_path / "p.log")
    children.append(publish)

    got = _receive_typed(ros, CompressedVideo, "/video_pkgtest_in")

    assert (got.frame_id, got.format, got.timestamp.sec) == ("front", "av1", 4)
    assert bytes(got.data) == payload[::-1]
    _context, peer = ros
    (info,) = peer.get_publishers_info_by_topic("/video_pkgtest_in")
    assert str(info.topic_type_hash) == typestore.hash_rihs01(VIDEO)
