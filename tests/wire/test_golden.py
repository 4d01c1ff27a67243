"""Golden byte fixtures: the wire format does not change by accident."""

from __future__ import annotations

import struct

import pytest

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.metadata import read_metadata

from .golden import FIXTURES, golden_cases

CASES = golden_cases(default_codec())


@pytest.mark.parametrize("stem", sorted(CASES))
def test_encoder_writes_the_golden_bytes(codec: Codec, stem: str) -> None:
    type_name, topic, msg, kwargs = CASES[stem]
    expected = FIXTURES.joinpath(f"{stem}.bin").read_bytes()
    assert codec.encode(msg, type_name, topic, **kwargs) == expected


@pytest.mark.parametrize("stem", sorted(CASES))
def test_golden_bytes_decode_to_the_message(codec: Codec, stem: str) -> None:
    type_name, topic, msg, _kwargs = CASES[stem]
    frame = FIXTURES.joinpath(f"{stem}.bin").read_bytes()
    meta, back = codec.decode(frame)
    assert (meta.type, meta.topic) == (type_name, topic)
    assert read_metadata(frame) == meta
    ts = codec.registry.typestore
    assert ts.serialize_cdr(back, type_name) == ts.serialize_cdr(msg, type_name)


def test_robofleet_subscription_bytes_are_readable_by_hand() -> None:
    """Robofleet readers only know fields 0 (type) and 1 (topic) of ``__metadata``."""
    frame = FIXTURES.joinpath("robofleet_subscription.bin").read_bytes()
    assert b"amrl_msgs/msg/RobofleetSubscription\x00" in frame
    assert b"/subscriptions\x00" in frame and b"/husky1/.*\x00" in frame


def test_latched_flag_sits_in_metadata_vtable_slot_5_by_hand() -> None:
    """The layout other readers rely on: slot 5 of ``__metadata``, one byte, value 1."""
    frame = FIXTURES.joinpath("robot_description_latched.bin").read_bytes()
    root = struct.unpack_from("<I", frame, 0)[0]
    vt = root - struct.unpack_from("<i", frame, root)[0]
    mpos = root + struct.unpack_from("<H", frame, vt + 4)[0]
    mtab = mpos + struct.unpack_from("<I", frame, mpos)[0]
    mvt = mtab - struct.unpack_from("<i", frame, mtab)[0]
    vt_bytes = struct.unpack_from("<H", frame, mvt)[0]
    assert vt_bytes == 4 + 2 * 6  # six slots: type, topic, no_drop, time, seq, latched
    latched_off = struct.unpack_from("<H", frame, mvt + 4 + 2 * 5)[0]
    assert latched_off and frame[mtab + latched_off] == 1
    assert read_metadata(frame).latched


def test_frames_from_before_the_latched_field_read_as_not_latched() -> None:
    for stem in ("robofleet_status", "laser_scan_small", "pose_stamped"):
        frame = FIXTURES.joinpath(f"{stem}.bin").read_bytes()
        assert read_metadata(frame).latched is False
