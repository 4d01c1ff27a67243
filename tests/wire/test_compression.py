"""Compressed frames: round trips, pass-through, and bounded, WireError-only decompression."""

from __future__ import annotations

import contextlib
import struct
import tracemalloc
import zlib
from typing import Any

import numpy as np
import pytest
import zstandard
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fleetctl.wire.codec import Codec
from fleetctl.wire.compression import (
    COMPRESSED_TYPE,
    MIN_SAVING,
    CompressionCodec,
    compress,
    decompress,
)
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import split
from fleetctl.wire.metadata import read_metadata
from fleetctl.wire.samples import compressed_image, laser_scan, occupancy_grid, point_cloud
from tests.support import compressed_frame, string_frame

CODECS = list(CompressionCodec)
MiB = 1 << 20
SAMPLES = {
    "nav_msgs/msg/OccupancyGrid": occupancy_grid,
    "sensor_msgs/msg/PointCloud2": point_cloud,
    "sensor_msgs/msg/LaserScan": laser_scan,
}


def _frame(codec: Codec, type_name: str, topic: str = "/r1/x", **kw: Any) -> bytes:
    msg = SAMPLES[type_name](codec.registry)
    return codec.encode(msg, type_name, topic, publish_time_ns=1_700_000_000_000_000_001,
                        seq=42, **kw)


@pytest.mark.parametrize("method", CODECS, ids=lambda c: c.name)
@pytest.mark.parametrize("type_name", list(SAMPLES))
def test_round_trip_copies_metadata(codec: Codec, type_name: str,
                                    method: CompressionCodec) -> None:
    original = _frame(codec, type_name, no_drop=True)
    packed = compress(original, codec=method, topic="/r1/x", no_drop=True)
    assert len(packed) <= len(original) * (1 - MIN_SAVING)
    meta = read_metadata(packed)
    assert (meta.type, meta.topic, meta.no_drop, meta.seq, meta.publish_time_ns) == (
        COMPRESSED_TYPE, "/r1/x", True, 42, 1_700_000_000_000_000_001)
    _meta, msg = codec.decode_as(packed, COMPRESSED_TYPE)
    assert (msg.codec, msg.original_bytes) == (method, len(original))
    assert decompress(packed, len(original)) == original
    assert codec.decode(decompress(packed, 64 * MiB))[0].type == type_name


@pytest.mark.parametrize("method", CODECS, ids=lambda c: c.name)
def test_compressed_frame_copies_the_latched_flag(codec: Codec, method: CompressionCodec) -> None:
    original = _frame(codec, "nav_msgs/msg/OccupancyGrid", latched=True)
    packed = compress(original, codec=method, topic="/r1/x", no_drop=False)
    meta = read_metadata(packed)
    assert (meta.type, meta.latched, meta.no_drop) == (COMPRESSED_TYPE, True, False)
    assert read_metadata(decompress(packed, 64 * MiB)).latched is True
    plain = compress(_frame(codec, "nav_msgs/msg/OccupancyGrid"), codec=method, topic="/r1/x",
                     no_drop=False)
    assert read_metadata(plain).latched is False
    # Compressed, then fragmented: every fragment still says latched.
    fragments = split(packed, topic="/r1/x", message_id=1, max_fragment_bytes=600,
                      no_drop=False)
    assert len(fragments) > 1 and all(read_metadata(f).latched for f in fragments)


def test_a_map_compresses_by_more_than_an_order_of_magnitude(codec: Codec) -> None:
    original = _frame(codec, "nav_msgs/msg/OccupancyGrid")
    for method in CODECS:
        assert len(compress(original, codec=method, topic="/r1/x", no_drop=False)) < (
            len(original) / 10)


@pytest.mark.parametrize("method", CODECS, ids=lambda c: c.name)
def test_incompressible_and_tiny_frames_pass_through_unchanged(
        codec: Codec, method: CompressionCodec) -> None:
    jpeg = codec.encode(compressed_image(codec.registry), "sensor_msgs/msg/CompressedImage",
                        "/r1/cam")
    tiny = string_frame("/r1/t", "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa")
    assert compress(jpeg, codec=method, topic="/r1/cam", no_drop=False) is jpeg
    assert compress(tiny, codec=method, topic="/r1/t", no_drop=False) is tiny


def test_other_frames_pass_through_decompress(codec: Codec) -> None:
    frame = string_frame("/r1/t", "plain")
    assert decompress(frame, 10) is frame


def test_compress_refuses_fragments_compressed_frames_and_another_topic(codec: Codec) -> None:
    original = _frame(codec, "nav_msgs/msg/OccupancyGrid")
    packed = compress(original, codec=CompressionCodec.ZSTD, topic="/r1/x", no_drop=False)
    fragment = split(original, topic="/r1/x", message_id=1, max_fragment_bytes=4096,
                     no_drop=False)[0]
    for frame in (packed, fragment):
        with pytest.raises(WireError, match="compress the original frame"):
            compress(frame, codec=CompressionCodec.ZSTD, topic="/r1/x", no_drop=False)
    with pytest.raises(WireError, match="not on '/r1/y'"):
        compress(original, codec=CompressionCodec.ZSTD, topic="/r1/y", no_drop=False)
    with pytest.raises(WireError):
        compress(b"\x00" * 16, codec=CompressionCodec.ZSTD, topic="/r1/x", no_drop=False)
    with pytest.raises(WireError, match="unknown compression codec 9"):
        compress(original, codec=9, topic="/r1/x", no_drop=False)  # type: ignore[arg-type]
    assert CompressionCodec.from_name("deflate") is CompressionCodec.DEFLATE
    with pytest.raises(ValueError, match="zstd or deflate"):
        CompressionCodec.from_name("gzip")


def _payloads(original: bytes) -> dict[CompressionCodec, bytes]:
    return {
        CompressionCodec.ZSTD: zstandard.ZstdCompressor().compress(original),
        CompressionCodec.DEFLATE: zlib.compress(original, 6, wbits=-15),
    }


@pytest.mark.parametrize("method", CODECS, ids=lambda c: c.name)
def test_corrupt_or_mismatched_content_is_a_wire_error(method: CompressionCodec) -> None:
    original = string_frame("/r1/x", "abc" * 1000)
    payload = _payloads(original)[method]

    def frame(payload: bytes = payload, original_bytes: int = len(original),
              topic: str = "/r1/x") -> bytes:
        return compressed_frame(topic, codec=int(method), original_bytes=original_bytes,
                                payload=payload)

    assert decompress(frame(), len(original)) == original
    cases = {
        "corrupt": frame(payload=bytes(b ^ 0x5A for b in payload)),
        "truncated": frame(payload=payload[: len(payload) // 2]),
        "trailing": frame(payload=payload + b"\x01\x02"),
        "empty": frame(payload=b""),
        "smaller": frame(original_bytes=len(original) - 1),
        "larger": frame(original_bytes=len(original) + 1),
        "too short": frame(original_bytes=4),
        "other topic": frame(topic="/r2/x"),
    }
    for label, bad in cases.items():
        with pytest.raises(WireError):
            decompress(bad, 10 * MiB)
            pytest.fail(f"{label}: accepted")


def test_unknown_codec_and_over_limit_are_wire_errors() -> None:
    original = string_frame("/r1/x", "abc" * 1000)
    payload = _payloads(original)[CompressionCodec.DEFLATE]
    with pytest.raises(WireError, match="unknown codec 3"):
        decompress(compressed_frame("/r1/x", codec=3, original_bytes=len(original),
                                    payload=payload), MiB)
    ok = compressed_frame("/r1/x", codec=2, original_bytes=len(original), payload=payload)
    with pytest.raises(WireError, match="over the limit"):
        decompress(ok, len(original) - 1)


def test_nested_compression_is_refused() -> None:
    inner = compress(string_frame("/r1/x", "z" * 5000), codec=CompressionCodec.ZSTD,
                     topic="/r1/x", no_drop=False)
    payload = zlib.compress(inner, 6, wbits=-15)
    outer = compressed_frame("/r1/x", codec=2, original_bytes=len(inner), payload=payload)
    with pytest.raises(WireError, match="holds a fleetctl_msgs/msg/Compressed frame"):
        decompress(outer, MiB)


def _peak_allocated_bytes(fn: Any) -> int:
    tracemalloc.start()
    try:
        with contextlib.suppress(WireError):
            fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_bombs_never_allocate_past_the_declared_size() -> None:
    """64 MiB of zeros compresses to a few KB; the receiver must not inflate it."""
    original = string_frame("/r1/x", "ok")
    zeros = original + bytes(64 * MiB)
    bombs = [
        # Declares a small frame; the data inflates to 64 MiB.
        compressed_frame("/r1/x", codec=2, original_bytes=1000,
                         payload=zlib.compress(zeros, 9, wbits=-15)),
        compressed_frame("/r1/x", codec=1, original_bytes=1000,
                         payload=zstandard.ZstdCompressor(write_content_size=False)
                         .compress(zeros)),
        # The zstd header declares 64 MiB (decompress() would allocate that up front).
        compressed_frame("/r1/x", codec=1, original_bytes=1000,
                         payload=zstandard.ZstdCompressor().compress(zeros)),
        # Declares 64 MiB, over the receiver's limit.
        compressed_frame("/r1/x", codec=2, original_bytes=len(zeros),
                         payload=zlib.compress(zeros, 9, wbits=-15)),
    ]
    for bomb in bombs:
        assert len(bomb) < 300_000
        with pytest.raises(WireError):
            decompress(bomb, MiB)
        assert _peak_allocated_bytes(lambda b=bomb: decompress(b, MiB)) < 2 * len(bomb) + MiB


def _decompress_or_wire_error(frame: bytes) -> None:
    with contextlib.suppress(WireError):
        out = decompress(frame, 4 * MiB)
        assert read_metadata(out).topic == read_metadata(frame).topic


_FUZZ_ORIGINAL = string_frame("/r1/x", "fuzz " * 400)
_FUZZ_FRAMES = [compress(_FUZZ_ORIGINAL, codec=m, topic="/r1/x", no_drop=False) for m in CODECS]


@settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(_FUZZ_FRAMES), st.data())
def test_mutated_compressed_frames_raise_only_wire_error(frame: bytes,
                                                         data: st.DataObject) -> None:
    mutated = bytearray(frame)
    for _ in range(data.draw(st.integers(1, 8))):
        pos = data.draw(st.integers(0, len(mutated) - 1))
        mutated[pos] = data.draw(st.integers(0, 255))
    if data.draw(st.booleans()):  # hostile 32-bit offsets, lengths and sizes
        pos = data.draw(st.integers(0, len(mutated) // 4 - 1)) * 4
        value = data.draw(st.sampled_from([0, 1, 0x7FFFFFFF, 0xFFFFFFFF, len(mutated)]))
        struct.pack_into("<I", mutated, pos, value)
    _decompress_or_wire_error(bytes(mutated[: data.draw(st.integers(0, len(mutated)))]))


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 255), st.integers(0, 0xFFFFFFFF), st.binary(max_size=256))
def test_arbitrary_content_raises_only_wire_error(method: int, original_bytes: int,
                                                  payload: bytes) -> None:
    _decompress_or_wire_error(compressed_frame("/r1/x", codec=method,
                                               original_bytes=original_bytes, payload=payload))


def test_compressed_is_a_registered_protocol_type(codec: Codec) -> None:
    cls = codec.registry.get(COMPRESSED_TYPE).cls
    assert (cls.ZSTD, cls.DEFLATE) == (1, 2)
    assert [f.name for f in codec.registry.get(COMPRESSED_TYPE).fields] == [
        "codec", "original_bytes", "payload"]
    empty = cls(1, 0, np.zeros(0, dtype=np.uint8))
    assert codec.decode(codec.encode(empty, COMPRESSED_TYPE, "/t"))[1].codec == 1


def test_a_higher_level_is_smaller_and_decodes_the_same(codec: Codec) -> None:
    from fleetctl.wire.compression import LATCHED_DEFLATE_LEVEL

    grid = occupancy_grid(codec.registry, 384)
    frame = codec.encode(grid, "nav_msgs/msg/OccupancyGrid", "/r1/map", latched=True)
    fast = compress(frame, codec=CompressionCodec.DEFLATE, topic="/r1/map", no_drop=False)
    best = compress(frame, codec=CompressionCodec.DEFLATE, topic="/r1/map", no_drop=False,
                    level=LATCHED_DEFLATE_LEVEL)
    assert len(best) < len(fast) < len(frame)
    assert decompress(best, len(frame)) == frame
    assert read_metadata(best).latched
    packed = compress(frame, codec=CompressionCodec.ZSTD, topic="/r1/map", no_drop=False,
                      level=9)
    assert decompress(packed, len(frame)) == frame
