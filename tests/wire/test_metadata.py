"""Tests of fleetctl.wire.metadata: normalization and the bounds-checked metadata reader."""

from __future__ import annotations

import contextlib
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.control import encode_status, encode_subscription
from fleetctl.wire.errors import WireError
from fleetctl.wire.metadata import (
    METADATA_TYPE,
    Metadata,
    normalize_type,
    read_metadata,
    read_root,
)

_LATCHED_STRING = default_codec().encode(
    default_codec().registry.get("std_msgs/msg/String").cls("map"), "std_msgs/msg/String",
    "/r1/map", no_drop=True, publish_time_ns=10, seq=3, latched=True)


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("sensor_msgs/msg/LaserScan", "sensor_msgs/msg/LaserScan"),
        ("sensor_msgs/LaserScan", "sensor_msgs/msg/LaserScan"),
        ("RobofleetSubscription", "amrl_msgs/msg/RobofleetSubscription"),
        ("RobofleetStatus", "amrl_msgs/msg/RobofleetStatus"),
        ("amrl_msgs/RobofleetStatus", "amrl_msgs/msg/RobofleetStatus"),
    ],
)
def test_normalize_type_accepts_ros1_ros2_and_bare_forms(name: str, expected: str) -> None:
    assert normalize_type(name) == expected


@pytest.mark.parametrize(
    "name", ["", "LaserScan", "a/b/c/d", "sensor_msgs/srv/X", "/x/Y", "x/ Y", "x/msg/", "é/X"]
)
def test_normalize_type_rejects_other_forms(name: str) -> None:
    with pytest.raises(WireError, match="bad message type name"):
        normalize_type(name)


def test_read_metadata_reads_all_fields(codec: Codec) -> None:
    msg = codec.registry.get("std_msgs/msg/String").cls("hi")
    frame = codec.encode(
        msg, "std_msgs/String", "/r1/events", no_drop=True, publish_time_ns=2**63 + 5, seq=42
    )
    assert read_metadata(frame) == Metadata(
        "std_msgs/msg/String", "/r1/events", True, 2**63 + 5, 42
    )
    assert read_metadata(memoryview(frame)) == read_metadata(frame)
    assert read_metadata(frame).latched is False


def test_read_metadata_reads_the_latched_flag(codec: Codec) -> None:
    msg = codec.registry.get("std_msgs/msg/String").cls("map")
    frame = codec.encode(msg, "std_msgs/msg/String", "/r1/map", latched=True, seq=3)
    assert read_metadata(frame) == Metadata("std_msgs/msg/String", "/r1/map", False, 0, 3, True)
    assert codec.decode(frame)[0].latched is True
    # Latched and every other field set: the flag does not disturb its neighbours.
    full = codec.encode(msg, "std_msgs/msg/String", "/r1/map", no_drop=True,
                        publish_time_ns=7, seq=9, latched=True)
    assert read_metadata(full) == Metadata("std_msgs/msg/String", "/r1/map", True, 7, 9, True)


def _frame_with_metadata_slots(codec: Codec, values: dict[int, tuple[str, object]]) -> bytes:
    """A String frame whose ``__metadata`` table has exactly the given slots (by hand)."""
    import flatbuffers

    builder = flatbuffers.Builder(128)
    strings = {slot: builder.CreateString(v) for slot, (kind, v) in values.items()
               if kind == "string"}
    text = builder.CreateString("x")
    builder.StartObject(1 + max(values))
    for slot, (kind, v) in values.items():
        if kind == "string":
            builder.PrependUOffsetTRelativeSlot(slot, strings[slot], 0)
        elif kind == "bool":
            builder.PrependBoolSlot(slot, bool(v), False)
        else:
            builder.PrependUint64Slot(slot, int(v), 0)  # type: ignore[call-overload]
    meta = builder.EndObject()
    builder.StartObject(2)
    builder.PrependUOffsetTRelativeSlot(1, text, 0)
    builder.PrependUOffsetTRelativeSlot(0, meta, 0)
    builder.Finish(builder.EndObject())
    return bytes(builder.Output())


def test_a_newer_writer_with_more_metadata_fields_is_read(codec: Codec) -> None:
    """Slots past latched (a future field) are ignored, as FlatBuffers readers do."""
    frame = _frame_with_metadata_slots(codec, {
        0: ("string", "std_msgs/msg/String"), 1: ("string", "/r1/t"), 2: ("bool", True),
        4: ("u64", 5), 5: ("bool", True), 6: ("u64", 99)})
    assert read_metadata(frame) == Metadata("std_msgs/msg/String", "/r1/t", True, 0, 5, True)
    assert codec.decode(frame)[1].data == "x"


def test_a_robofleet_writer_without_delivery_fields_is_not_latched(codec: Codec) -> None:
    frame = _frame_with_metadata_slots(codec, {
        0: ("string", "std_msgs/msg/String"), 1: ("string", "/r1/t")})
    assert read_metadata(frame) == Metadata("std_msgs/msg/String", "/r1/t")


def test_read_metadata_agrees_with_generic_decoder(codec: Codec) -> None:
    frame = encode_status("husky1", status="ok", is_ok=True, battery_level=0.5, seq=7)
    meta, root = read_root(frame)
    # Follow field 0 of the root table by hand, then decode it with the generic codec.
    vt = root - struct.unpack_from("<i", frame, root)[0]
    mpos = root + struct.unpack_from("<H", frame, vt + 4)[0]
    mtab = mpos + struct.unpack_from("<I", frame, mpos)[0]
    generic = codec.decode_table(frame, METADATA_TYPE, mtab)
    assert tuple(getattr(generic, f) for f in Metadata._fields) == tuple(meta)


def test_robofleet_style_type_names_are_normalized_on_read(codec: Codec) -> None:
    cls = codec.registry.get(METADATA_TYPE).cls
    import flatbuffers

    from fleetctl.wire.encoder import EncoderFactory

    # A frame as Robofleet writes it: bare control type name in __metadata.type.
    enc = EncoderFactory(codec.registry)
    builder = flatbuffers.Builder(64)
    meta = enc.table(METADATA_TYPE)(builder, cls("RobofleetSubscription", "/subscriptions",
                                                  False, 0, 0, False), 0)
    sub = codec.registry.get("amrl_msgs/msg/RobofleetSubscription").cls("/a/.*", 1)
    builder.Finish(enc.table("amrl_msgs/msg/RobofleetSubscription")(builder, sub, meta))
    frame = bytes(builder.Output())
    assert read_metadata(frame).type == "amrl_msgs/msg/RobofleetSubscription"
    assert codec.decode(frame)[1].topic_regex == "/a/.*"


@pytest.mark.parametrize("cut", [0, 1, 4, 7, 8, 20, -1, -5])
def test_truncated_frames_raise_wire_error(cut: int) -> None:
    frame = encode_subscription("/husky1/.*")
    with pytest.raises(WireError):
        read_metadata(frame[:cut])


def test_frame_without_metadata_is_rejected(codec: Codec) -> None:
    import flatbuffers

    builder = flatbuffers.Builder(16)
    builder.StartObject(2)
    builder.PrependUint8Slot(1, 1, 0)
    builder.Finish(builder.EndObject())
    with pytest.raises(WireError, match="no __metadata"):
        read_metadata(bytes(builder.Output()))


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_give_wire_error_or_metadata(data: bytes) -> None:
    with contextlib.suppress(WireError):
        assert isinstance(read_metadata(data), Metadata)


@settings(max_examples=600, deadline=None)
@given(st.data())
def test_mutated_frames_give_wire_error_or_metadata(data: st.DataObject) -> None:
    frame = bytearray(encode_status("robot7", status="fine", is_ok=True, battery_level=0.9,
                                    location="dock", seq=3, publish_time_ns=10))
    if data.draw(st.booleans()):
        frame = bytearray(_LATCHED_STRING)
    for _ in range(data.draw(st.integers(1, 6))):
        pos = data.draw(st.integers(0, len(frame) - 1))
        frame[pos] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(frame)))
    with contextlib.suppress(WireError):
        assert isinstance(read_metadata(bytes(frame[:cut])), Metadata)
