"""Is this encoded video frame a keyframe? Read from the bitstream, codec by codec.

``foxglove_msgs/msg/CompressedVideo`` carries no keyframe flag: a viewer that lost a frame
must find the next frame it can start from in the data itself. These readers look at the
first bytes only (no decoding) and follow the specifications cited per function. Pure
Python, no I/O: :class:`fleetctl.client.video.VideoDecoder` and the tests use them, and the
web page's ``js/videocodec.js`` applies the same rules.
"""

from __future__ import annotations

from collections.abc import Iterator

__all__ = ["h264_nal_types", "is_keyframe"]

_H264_IDR = 5
_AV1_OBU_SEQUENCE_HEADER = 1
_AV1_OBU_FRAME_HEADER = 3
_AV1_OBU_FRAME = 6
_AV1_KEY_FRAME = 0


def is_keyframe(codec: str, data: bytes | memoryview) -> bool:
    """True when *data* (one CompressedVideo frame) can be decoded without earlier frames.

    Args:
        codec: The CompressedVideo ``format``: ``h264``, ``vp8``, ``vp9`` or ``av1``.
        data: One encoded frame as :class:`fleetctl.client.video.VideoEncoder` emits it.

    Returns:
        False for a delta frame, for data too short or malformed to tell, and for an
        unknown codec (a viewer must not start from a frame it cannot classify).
    """
    view = memoryview(data).cast("B")
    try:
        if codec == "h264":
            return _H264_IDR in h264_nal_types(view)
        if codec == "vp8":
            return _vp8_keyframe(view)
        if codec == "vp9":
            return _vp9_keyframe(view)
        if codec == "av1":
            return _av1_keyframe(view)
    except IndexError:  # truncated: not something to start decoding from
        return False
    return False


def h264_nal_types(data: memoryview) -> list[int]:
    """The ``nal_unit_type`` of every NAL unit of an Annex B byte stream (H.264 Annex B.1:
    units start after ``00 00 01``; the type is the low five bits of the first byte)."""
    return [data[start] & 0x1F for start in _annexb_starts(data) if start < len(data)]


def _annexb_starts(data: memoryview) -> Iterator[int]:
    raw = data.tobytes() if len(data) <= 4096 else data[:4096].tobytes()
    # SPS, PPS and the IDR slice header come first: the first 4 KiB hold their start codes
    # (a keyframe's slice data can be tens of kilobytes that need no scan).
    i = raw.find(b"\x00\x00\x01")
    while i >= 0:
        yield i + 3
        i = raw.find(b"\x00\x00\x01", i + 3)


def _vp8_keyframe(data: memoryview) -> bool:
    # RFC 6386 section 9.1: the frame tag's bit 0 is 0 for a key frame, and a key frame's
    # tag is followed by the start code 9d 01 2a.
    return (data[0] & 1) == 0 and data[3:6].tobytes() == b"\x9d\x01\x2a"


def _vp9_keyframe(data: memoryview) -> bool:
    # VP9 bitstream specification section 6.2 (uncompressed_header): frame_marker (2 bits,
    # 0b10), profile_low_bit, profile_high_bit, reserved_zero when the profile is 3,
    # show_existing_frame, frame_type (0 = KEY_FRAME).
    bits = _Bits(data)
    if bits.read(2) != 2:
        return False
    profile = bits.read(1) | (bits.read(1) << 1)
    if profile == 3:
        bits.read(1)
    if bits.read(1):  # show_existing_frame: repeats a decoded frame, references it
        return False
    return bits.read(1) == 0


def _av1_keyframe(data: memoryview) -> bool:
    # AV1 specification section 5.3 (OBU header) and 5.9.2 (uncompressed_header): the first
    # frame header's frame_type, after show_existing_frame, is 0 for KEY_FRAME. Encoders
    # emit a sequence header before every key frame, which the frame header's layout
    # depends on; reduced_still_picture_header streams (still images) are not video.
    pos = 0
    seen_sequence_header = False
    while pos < len(data):
        header = data[pos]
        obu_type = (header >> 3) & 0x0F
        has_extension = (header >> 2) & 1
        has_size = (header >> 1) & 1
        pos += 1 + has_extension
        if has_size:
            size, pos = _leb128(data, pos)
        else:
            size = len(data) - pos
        if obu_type == _AV1_OBU_SEQUENCE_HEADER:
            seen_sequence_header = True
        elif obu_type in (_AV1_OBU_FRAME_HEADER, _AV1_OBU_FRAME):
            bits = _Bits(data[pos:pos + size])
            if bits.read(1):  # show_existing_frame
                return False
            return seen_sequence_header and bits.read(2) == _AV1_KEY_FRAME
        pos += size
    return False


def _leb128(data: memoryview, pos: int) -> tuple[int, int]:
    """AV1 section 4.10.5: little-endian base-128 (at most 8 bytes); returns value, end."""
    value = 0
    for i in range(8):
        byte = data[pos + i]
        value |= (byte & 0x7F) << (7 * i)
        if not byte & 0x80:
            return value, pos + i + 1
    raise IndexError("leb128 longer than 8 bytes")


class _Bits:
    """Most-significant-bit-first reader (as both VP9 and AV1 headers are written)."""

    def __init__(self, data: memoryview) -> None:
        self._data = data
        self._pos = 0

    def read(self, count: int) -> int:
        value = 0
        for _ in range(count):
            byte = self._data[self._pos >> 3]
            value = (value << 1) | ((byte >> (7 - (self._pos & 7))) & 1)
            self._pos += 1
        return value
