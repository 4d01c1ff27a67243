"""ros2msg schemas and frame -> CDR transcoding, checked against rosbags as the reference."""

from __future__ import annotations

import random
import subprocess
import sys

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from fleetctl.wire import fragments, samples
from fleetctl.wire.codec import Codec
from fleetctl.wire.compression import CompressionCodec, compress
from fleetctl.wire.errors import WireError
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.ros2msg import FrameTranscoder, schema_text, type_hash
from tests.wire.synth import message

TYPES = ["geometry_msgs/msg/PoseStamped", "sensor_msgs/msg/LaserScan",
         "sensor_msgs/msg/PointCloud2", "nav_msgs/msg/OccupancyGrid",
         "tf2_msgs/msg/TFMessage", "amrl_msgs/msg/RobofleetStatus"]


def test_schema_text_is_rosbag2_layout(registry: TypeRegistry) -> None:
    text = schema_text(registry, "geometry_msgs/PoseStamped")  # the ROS 1 form is accepted
    own, *deps = text.split("=" * 80 + "\n")
    assert own.splitlines()[:2] == ["std_msgs/Header header", "geometry_msgs/Pose pose"]
    names = [d.splitlines()[0] for d in deps]
    assert names[0] == "MSG: std_msgs/Header"  # rosbag2 writes pkg/Name in MSG: lines
    assert "MSG: builtin_interfaces/Time" in names
    assert "MSG: geometry_msgs/Quaternion" in names


@pytest.mark.parametrize("name", TYPES)
def test_schema_text_parses_back_to_the_same_definition(registry: TypeRegistry,
                                                        name: str) -> None:
    # What a reader (rosbags' AnyReader, Foxglove) does with the schema: parse every part
    # into an empty store; the result must describe the type as the registry does.
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(schema_text(registry, name), name))
    assert store.fielddefs[name] == registry.typestore.fielddefs[name]
    assert store.hash_rihs01(name) == type_hash(registry, name)


def test_unknown_type_is_a_wire_error(registry: TypeRegistry) -> None:
    with pytest.raises(WireError, match="no_such_pkg/msg/Nope"):
        schema_text(registry, "no_such_pkg/msg/Nope")


@pytest.mark.parametrize("name", TYPES)
def test_transcoded_cdr_decodes_with_rosbags_to_the_message(codec: Codec, name: str) -> None:
    msg = message(codec.registry, name, random.Random(name))
    frame = codec.encode(msg, name, "/r/t", publish_time_ns=123, seq=7)
    out = FrameTranscoder(codec, 1 << 20).feed(1, frame, 0.0)
    assert out is not None and out.type == name
    assert (out.meta.topic, out.meta.publish_time_ns, out.meta.seq) == ("/r/t", 123, 7)
    # An independent store (rosbags' own Jazzy definitions) deserializes the CDR.
    reference = get_typestore(Stores.ROS2_JAZZY) if name.split("/")[0] != "amrl_msgs" \
        else codec.registry.typestore
    back = reference.deserialize_cdr(out.cdr, name)
    assert reference.serialize_cdr(back, name).tobytes() == out.cdr
    assert codec.encode(back, name, "/r/t", publish_time_ns=123, seq=7) == frame


def test_fragments_are_reassembled_per_sender(codec: Codec) -> None:
    cloud = samples.point_cloud(codec.registry, 4, 1024)
    frame = codec.encode(cloud, "sensor_msgs/msg/PointCloud2", "/r/cloud", publish_time_ns=5)
    parts = fragments.split(frame, topic="/r/cloud", message_id=1, max_fragment_bytes=16_384,
                            no_drop=False)
    assert len(parts) > 3
    transcoder = FrameTranscoder(codec, 1 << 24)
    # Two senders interleave fragments of the same topic and message id: never mixed.
    results = []
    for part in parts:
        results.append(transcoder.feed("a", part, 0.0))
        results.append(transcoder.feed("b", part, 0.0))
    done = [r for r in results if r is not None]
    assert len(done) == 2 and all(r is None for r in results[:-2])
    expected = codec.registry.typestore.serialize_cdr(cloud, "sensor_msgs/msg/PointCloud2")
    assert done[0].cdr == done[1].cdr == expected.tobytes()
    assert done[0].meta.publish_time_ns == 5


@pytest.mark.parametrize("kind", [CompressionCodec.ZSTD, CompressionCodec.DEFLATE])
def test_compressed_frames_are_decompressed(codec: Codec, kind: CompressionCodec) -> None:
    grid = samples.occupancy_grid(codec.registry)
    frame = codec.encode(grid, "nav_msgs/msg/OccupancyGrid", "/r/map", seq=3)
    packed = compress(frame, codec=kind, topic="/r/map", no_drop=False)
    assert len(packed) < len(frame) // 4
    out = FrameTranscoder(codec, 1 << 24).feed(1, packed, 0.0)
    assert out is not None and out.type == "nav_msgs/msg/OccupancyGrid" and out.meta.seq == 3
    back = codec.registry.typestore.deserialize_cdr(out.cdr, out.type)
    assert np.array_equal(back.data, grid.data)


def test_malformed_frames_raise_wire_error(codec: Codec) -> None:
    transcoder = FrameTranscoder(codec, 1 << 20)
    frame = codec.encode(codec.registry.get("std_msgs/msg/String").cls("hi"),
                         "std_msgs/msg/String", "/r/chat")
    with pytest.raises(WireError):
        transcoder.feed(1, b"\x00" * 16, 0.0)
    with pytest.raises(WireError):
        transcoder.feed(1, frame[: len(frame) - 6], 0.0)


def test_senders_are_bounded(codec: Codec) -> None:
    cloud = samples.point_cloud(codec.registry, 2, 512)
    frame = codec.encode(cloud, "sensor_msgs/msg/PointCloud2", "/r/cloud")
    first = fragments.split(frame, topic="/r/cloud", message_id=1, max_fragment_bytes=4096,
                            no_drop=False)[0]
    transcoder = FrameTranscoder(codec, 1 << 20, max_senders=4)
    for sender in range(10):
        assert transcoder.feed(sender, first, 0.0) is None
    assert len(transcoder._reassemblers) == 4


def test_pending_bytes_of_all_senders_are_bounded(codec: Codec) -> None:
    cloud = samples.point_cloud(codec.registry, 4, 1024)  # ~64 KiB
    frame = codec.encode(cloud, "sensor_msgs/msg/PointCloud2", "/r/cloud")
    parts = fragments.split(frame, topic="/r/cloud", message_id=1, max_fragment_bytes=8192,
                            no_drop=False)
    transcoder = FrameTranscoder(codec, 1 << 20, max_pending_bytes=3 * len(frame))
    for sender in range(6):  # six partial messages: only three fit
        assert transcoder.feed(sender, parts[0], 0.0) is None
    assert len(transcoder._reassemblers) == 3 and transcoder.evicted_senders == 3
    # The newest senders were kept: one of them completes its message.
    done = [transcoder.feed(5, p, 0.0) for p in parts[1:]]
    assert done[-1] is not None and done[-1].type == "sensor_msgs/msg/PointCloud2"


def test_ros2msg_imports_no_io_modules() -> None:
    # The wire room: the Foxglove adapter and the recorder's worker share this module.
    code = ("import sys, fleetctl.wire.ros2msg\n"
            "print(sorted(m for m in ('asyncio', 'websockets', 'rclpy', 'mcap') "
            "if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True).stdout
    assert out.strip() == "[]"
