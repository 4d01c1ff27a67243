"""Round trips of the generic codec over every known type, checked through CDR."""

from __future__ import annotations

import random
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.errors import WireError
from fleetctl.wire.metadata import METADATA_TYPE
from fleetctl.wire.registry import TypeRegistry

from .synth import message

ALL_TYPES = [n for n in default_codec().registry.names() if n != METADATA_TYPE]


def _cdr(registry: TypeRegistry, msg: Any, name: str) -> bytes:
    return bytes(registry.typestore.serialize_cdr(msg, name))


def test_the_store_is_all_there() -> None:
    assert len(ALL_TYPES) >= 162 + 4  # Jazzy store + amrl_msgs (2) + Fragment + Compressed
    assert {"amrl_msgs/msg/RobofleetStatus", "fleetctl_msgs/msg/Fragment",
            "fleetctl_msgs/msg/Compressed",
            "sensor_msgs/msg/PointCloud2", "tf2_msgs/msg/TFMessage"} <= set(ALL_TYPES)


@pytest.mark.parametrize("name", ALL_TYPES)
def test_round_trip_every_type(codec: Codec, name: str) -> None:
    registry = codec.registry
    for seed in range(3):
        msg = message(registry, name, random.Random(seed), max_len=4 * seed)
        frame = codec.encode(msg, name, "/robot/topic", seq=seed)
        meta, back = codec.decode(frame)
        assert (meta.type, meta.topic, meta.seq) == (name, "/robot/topic", seed)
        # CDR bytes are a complete, type-aware equality check (numpy arrays included).
        assert _cdr(registry, back, name) == _cdr(registry, msg, name)


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(ALL_TYPES), st.integers(0, 2**32), st.integers(0, 6))
def test_round_trip_random(name: str, seed: int, max_len: int) -> None:
    codec = default_codec()
    msg = message(codec.registry, name, random.Random(seed), max_len)
    _meta, back = codec.decode(codec.encode(msg, name, "/t"))
    assert _cdr(codec.registry, back, name) == _cdr(codec.registry, msg, name)


def test_arrays_come_back_as_owned_numpy_arrays(codec: Codec) -> None:
    cls = codec.registry.get("std_msgs/msg/Float64MultiArray").cls
    layout = codec.registry.get("std_msgs/msg/MultiArrayLayout").cls([], 0)
    data = np.linspace(0, 1, 1000)
    frame = bytearray(codec.encode(cls(layout, data), "std_msgs/Float64MultiArray", "/t"))
    _meta, back = codec.decode(bytes(frame))
    assert back.data.dtype == np.float64 and back.data.flags.writeable
    assert np.array_equal(back.data, data)


def test_encode_accepts_bytes_and_lists_for_arrays(codec: Codec) -> None:
    cls = codec.registry.get("sensor_msgs/msg/CompressedImage").cls
    header = codec.registry.get("std_msgs/msg/Header").cls(
        codec.registry.get("builtin_interfaces/msg/Time").cls(1, 2), "cam")
    _meta, back = codec.decode(codec.encode(cls(header, "jpeg", b"\xff\xd8\x00"),
                                            "sensor_msgs/CompressedImage", "/c"))
    assert back.data.tobytes() == b"\xff\xd8\x00"
    _meta, back = codec.decode(codec.encode(cls(header, "jpeg", [1, 2, 3]),
                                            "sensor_msgs/CompressedImage", "/c"))
    assert back.data.tolist() == [1, 2, 3]


@pytest.mark.parametrize(
    ("name", "field", "value", "match"),
    [
        ("geometry_msgs/msg/PoseWithCovariance", "covariance", np.zeros(35), "36 elements"),
        ("std_msgs/msg/UInt8", "data", 256, "std_msgs/msg/UInt8.data"),
        ("std_msgs/msg/String", "data", 5, "std_msgs/msg/String.data"),
        ("rcl_interfaces/msg/ParameterDescriptor", "integer_range", [None, None], "bounded"),
    ],
)
def test_values_that_do_not_fit_are_wire_errors(
    codec: Codec, name: str, field: str, value: Any, match: str
) -> None:
    msg = message(codec.registry, name, random.Random(0))
    setattr(msg, field, value)
    with pytest.raises(WireError, match=match):
        codec.encode(msg, name, "/t")


def test_unknown_type_is_a_wire_error(codec: Codec) -> None:
    with pytest.raises(WireError, match="unknown message type"):
        codec.encode(object(), "nope_msgs/msg/Nothing", "/t")


def test_the_metadata_table_is_not_a_message_type(codec: Codec) -> None:
    meta = message(codec.registry, METADATA_TYPE, random.Random(0))
    with pytest.raises(WireError, match="not a message type"):
        codec.encode(meta, METADATA_TYPE, "/t")


def test_nested_absent_tables_decode_as_defaults(codec: Codec) -> None:
    import flatbuffers

    from fleetctl.wire.encoder import EncoderFactory
    from fleetctl.wire.metadata import METADATA_TYPE

    # A PoseStamped frame with only metadata: every field takes its default.
    enc = EncoderFactory(codec.registry)
    builder = flatbuffers.Builder(64)
    meta_cls = codec.registry.get(METADATA_TYPE).cls
    meta = enc.table(METADATA_TYPE)(builder, meta_cls("geometry_msgs/msg/PoseStamped", "/p",
                                                      False, 0, 0, False), 0)
    builder.StartObject(3)
    builder.PrependUOffsetTRelativeSlot(0, meta, 0)
    builder.Finish(builder.EndObject())
    _meta, msg = codec.decode(bytes(builder.Output()))
    assert msg.header.frame_id == "" and msg.header.stamp.sec == 0
    assert msg.pose.orientation.w == 0.0


def test_large_point_cloud_is_not_copied_element_by_element(codec: Codec) -> None:
    """A 1 MB cloud encodes and decodes with whole-vector copies: far below per-element cost."""
    import time

    from fleetctl.wire.samples import point_cloud

    cloud = point_cloud(codec.registry)
    assert len(cloud.data) >= 1_000_000
    start = time.perf_counter()
    frame = codec.encode(cloud, "sensor_msgs/msg/PointCloud2", "/r/points")
    _meta, back = codec.decode(frame)
    elapsed_s = time.perf_counter() - start
    assert np.array_equal(back.data, cloud.data)
    # A Python loop over 1.2 M bytes takes > 50 ms here; whole copies take ~1 ms.
    assert elapsed_s < 0.05


def test_uninitialized_builder_memory_never_reaches_a_frame(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # new_builder starts large buffers uninitialized; here every buffer starts as garbage
    # (0xA5), and each frame must still be byte-identical to one built on zeroes.
    import fleetctl.wire.codec as codec_module

    reference = Codec(TypeRegistry.default())
    garbage = Codec(TypeRegistry.default())
    messages = [(name, message(reference.registry, name, random.Random(seed), max_len=3 * seed))
                for name in ALL_TYPES for seed in range(3)]
    expected = [reference.encode(msg, name, "/r/t", seq=7) for name, msg in messages]
    monkeypatch.setattr(codec_module, "_UNINITIALIZED_FROM_BYTES", 0)
    monkeypatch.setattr(codec_module, "np", type("GarbageNumpy", (), {
        "uint8": np.uint8,
        "empty": staticmethod(lambda n, dtype: np.full(n, 0xA5, dtype=dtype))}))
    assert codec_module.new_builder(64).Bytes[0] == 0xA5  # the garbage path is taken
    got = [garbage.encode(msg, name, "/r/t", seq=7) for name, msg in messages]
    assert got == expected
