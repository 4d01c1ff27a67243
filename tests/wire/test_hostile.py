"""Random and mutated frames give WireError from the decoder, and nothing else, quickly."""

from __future__ import annotations

import contextlib
import random
import struct
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fleetctl.wire.codec import default_codec
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import Reassembler
from fleetctl.wire.metadata import read_metadata

from .synth import message

SAMPLE_TYPES = [
    "sensor_msgs/msg/LaserScan", "sensor_msgs/msg/PointCloud2", "nav_msgs/msg/Path",
    "visualization_msgs/msg/MarkerArray", "rcl_interfaces/msg/ParameterEvent",
    "tf2_msgs/msg/TFMessage", "geometry_msgs/msg/PoseWithCovarianceStamped",
    "amrl_msgs/msg/RobofleetStatus", "fleetctl_msgs/msg/Fragment", "fleetctl_msgs/msg/Compressed",
    "trajectory_msgs/msg/MultiDOFJointTrajectory", "sensor_msgs/msg/JointState",
]
_FRAMES = {
    # Every other type latched, so mutations also hit MsgMetadata's trailing flag.
    name: default_codec().encode(message(default_codec().registry, name, random.Random(3), 3),
                                 name, "/robot/t", seq=1, latched=i % 2 == 0)
    for i, name in enumerate(SAMPLE_TYPES)
}


def _decode_or_wire_error(frame: bytes) -> None:
    with contextlib.suppress(WireError):
        default_codec().decode(frame)
    with contextlib.suppress(WireError):
        Reassembler(1 << 16, 1.0).feed(frame, 0.0)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=512))
def test_random_bytes(data: bytes) -> None:
    _decode_or_wire_error(data)


@settings(max_examples=800, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(SAMPLE_TYPES), st.data())
def test_mutated_frames(name: str, data: st.DataObject) -> None:
    frame = bytearray(_FRAMES[name])
    for _ in range(data.draw(st.integers(1, 8))):
        pos = data.draw(st.integers(0, len(frame) - 1))
        frame[pos] = data.draw(st.integers(0, 255))
    _decode_or_wire_error(bytes(frame[: data.draw(st.integers(0, len(frame)))]))


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(SAMPLE_TYPES), st.data())
def test_mutated_offsets(name: str, data: st.DataObject) -> None:
    """Overwrite aligned 32-bit words (offsets and lengths) with hostile values."""
    frame = bytearray(_FRAMES[name])
    for _ in range(data.draw(st.integers(1, 3))):
        pos = data.draw(st.integers(0, len(frame) // 4 - 1)) * 4
        value = data.draw(st.sampled_from([0, 1, 4, 0x7FFFFFFF, 0xFFFFFFFF, 0x80000000,
                                           len(frame), len(frame) - pos]))
        struct.pack_into("<I", frame, pos, value & 0xFFFFFFFF)
    _decode_or_wire_error(bytes(frame))


def test_shared_offsets_cannot_amplify_work() -> None:
    """A vector whose elements all point at one big table is rejected, not decoded N times."""
    codec = default_codec()
    registry = codec.registry
    path_cls = registry.get("nav_msgs/msg/Path").cls
    poses = [message(registry, "geometry_msgs/msg/PoseStamped", random.Random(i))
             for i in range(200)]
    for pose in poses:
        pose.header.frame_id = ""
    poses[0].header.frame_id = "x" * 5000
    frame = bytearray(codec.encode(path_cls(poses[1].header, poses), "nav_msgs/msg/Path", "/p"))
    # Point every element of the poses vector (length 200) at the first element's table.
    at = frame.index(struct.pack("<I", 200))
    first = at + 4 + struct.unpack_from("<I", frame, at + 4)[0]
    for i in range(200):
        slot = at + 4 + 4 * i
        struct.pack_into("<I", frame, slot, first - slot)
    assert len(frame) < 200 * 5000 // 10
    start = time.perf_counter()
    with pytest.raises(WireError, match="more bytes than"):
        codec.decode(bytes(frame))
    assert time.perf_counter() - start < 1.0


def test_read_metadata_cost_does_not_depend_on_message_size() -> None:
    from fleetctl.wire.samples import point_cloud

    big = default_codec().encode(point_cloud(default_codec().registry), "sensor_msgs/PointCloud2",
                                 "/r/points")
    small = _FRAMES["amrl_msgs/msg/RobofleetStatus"]
    assert read_metadata(big).topic == "/r/points"

    def cost(frame: bytes) -> float:
        start = time.perf_counter()
        for _ in range(2000):
            read_metadata(frame)
        return time.perf_counter() - start

    assert cost(big) < 3 * cost(small) + 0.01
