"""Unit tests of keyframe detection, on hand-built bitstream headers (the specs' layouts)."""

from __future__ import annotations

import pytest

from fleetctl.client.videobits import h264_nal_types, is_keyframe


def test_h264_idr_is_a_keyframe_and_a_p_slice_is_not() -> None:
    sps, pps = b"\x00\x00\x00\x01\x67\x64\x00\x1e", b"\x00\x00\x00\x01\x68\xeb"
    idr, p_slice = b"\x00\x00\x01\x65\x88\x84", b"\x00\x00\x00\x01\x41\x9a"
    assert h264_nal_types(memoryview(sps + pps + idr)) == [7, 8, 5]
    assert is_keyframe("h264", sps + pps + idr)
    assert not is_keyframe("h264", p_slice)
    assert not is_keyframe("h264", sps + pps)  # headers alone are not a picture


def test_vp8_frame_tag() -> None:
    # RFC 6386 9.1: key frame = bit 0 clear, then the start code 9d 01 2a.
    key = bytes([0x50, 0x42, 0x00, 0x9D, 0x01, 0x2A, 0x80, 0x02])
    inter = bytes([0x51, 0x42, 0x00, 0x9D, 0x01, 0x2A])
    assert is_keyframe("vp8", key)
    assert not is_keyframe("vp8", inter)
    assert not is_keyframe("vp8", key[:3])  # truncated


@pytest.mark.parametrize("first, key", [
    (0b1000_0010, True),   # marker 10, profile 0, show_existing 0, frame_type 0 (KEY)
    (0b1000_0110, False),  # frame_type 1 (non-key)
    (0b1000_1000, False),  # show_existing_frame: not a new picture
    (0b1011_0001, True),   # profile 3: reserved bit, show_existing 0, frame_type 0
    (0b0100_0010, False),  # bad frame marker
])
def test_vp9_uncompressed_header(first: int, key: bool) -> None:
    assert is_keyframe("vp9", bytes([first, 0x49, 0x83, 0x42])) is key


def _obu(obu_type: int, payload: bytes) -> bytes:
    # OBU header: type in bits 6..3, has_size_field bit 1; then leb128 size.
    return bytes([(obu_type << 3) | 0b10, len(payload)]) + payload


def test_av1_key_frame_after_a_sequence_header() -> None:
    temporal_delimiter = _obu(2, b"")
    sequence_header = _obu(1, b"\x00\x00\x00")
    key_frame = _obu(6, bytes([0b0001_0000]))  # show_existing 0, frame_type 00 (KEY)
    inter_frame = _obu(6, bytes([0b0010_0000]))  # frame_type 01 (INTER)
    assert is_keyframe("av1", temporal_delimiter + sequence_header + key_frame)
    assert not is_keyframe("av1", temporal_delimiter + inter_frame)
    # A key frame header without the sequence header cannot start a decoder.
    assert not is_keyframe("av1", temporal_delimiter + key_frame)
    # The last OBU may omit its size field.
    assert is_keyframe("av1", sequence_header + bytes([6 << 3, 0b0001_0000]))
    # A size field running past the data is truncated input.
    assert not is_keyframe("av1", sequence_header + bytes([(6 << 3) | 2, 0x80]))


def test_unknown_codec_and_empty_data_are_never_keyframes() -> None:
    assert not is_keyframe("h265", b"\x00\x00\x01\x26\x01")
    for codec in ("h264", "vp8", "vp9", "av1"):
        assert not is_keyframe(codec, b"")
