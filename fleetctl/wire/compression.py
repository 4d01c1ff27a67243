"""Optional per-topic compression: a whole frame inside a ``fleetctl_msgs/msg/Compressed``.

``Compressed {uint8 codec; uint32 original_bytes; uint8[] payload}`` carries the compressed
bytes of a whole encoded frame (its metadata included); its own metadata copies the
original's topic, no_drop, publish time, seq and latched flag, so the server routes it like
any frame (``docs/design.md`` section 1). Pipeline: the sender encodes, compresses, then fragments;
a receiver reassembles, decompresses, then decodes.

Two codecs (``docs/wire.md``): zstd for fleetctl clients (best ratio per CPU second), raw
deflate (RFC 1951) for topics a web page shows, because browsers decode deflate natively
(``DecompressionStream('deflate-raw')``) and none decodes zstd.

Decompression is bounded: nothing is allocated past ``original_bytes``, which must be at
most the receiver's ``max_bytes``; corrupt data, a size that differs from
``original_bytes``, an unknown codec and trailing garbage raise :class:`WireError`.
"""

from __future__ import annotations

import threading
import zlib
from enum import IntEnum

import numpy as np
import zstandard

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import FRAGMENT_TYPE
from fleetctl.wire.metadata import read_metadata

COMPRESSED_TYPE = "fleetctl_msgs/msg/Compressed"
_U32_MAX = 0xFFFFFFFF
_MIN_FRAME_BYTES = 8  # the smallest FlatBuffer with a root offset and a table

MIN_SAVING = 0.05
"""A Compressed frame is sent only when it is at least this fraction smaller than the
original. Below that the receiver's decompression (and, in a browser, an asynchronous hop
that delays the message) costs more than the few bytes save; it also keeps incompressible
data (JPEG, random-looking floats) on the plain path at the cost of one trial compression."""

ZSTD_LEVEL = 1
"""zstd level (``benchmarks/encoding_size.py --levels``, docs/benchmarks.md): level 3 makes a
384 x 384 map 6 % smaller (2.0 vs 2.1 kB, both ~0.1 ms) but costs 1.3-1.4x more on a 1 MiB
cloud (2.3-3.8 vs 1.7-2.7 ms) for the same size; sensor topics dominate the CPU."""

DEFLATE_LEVEL = 1
"""deflate level (same measurements): level 6 makes the map 40 % smaller (3.1 vs 5.2 kB out
of 148 kB; 1.8 vs 0.5 ms), but on float clouds, where no level gains over 1 %, it costs
1.5x more (15 vs 10 ms for the demo's 240 kB cloud); deflate is on the robot's CPU budget
for every topic the web page shows, and a map is small at either level."""


class CompressionCodec(IntEnum):
    """The ``codec`` field of a Compressed frame (constants of ``Compressed.msg``)."""

    ZSTD = 1
    DEFLATE = 2

    @classmethod
    def from_name(cls, name: str) -> CompressionCodec:
        """``"zstd"`` or ``"deflate"`` (the names used in ``client.yaml``).

        Raises:
            ValueError: Any other name.
        """
        try:
            return cls[name.upper()]
        except KeyError:
            raise ValueError(f"unknown compression codec {name!r} (zstd or deflate)") from None


class _Contexts(threading.local):
    """zstd contexts, one set per thread: creating one per message costs more than a small
    message's compression, and a context must not be used by two threads at once."""

    def __init__(self) -> None:
        self.compressor = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
        self.decompressor = zstandard.ZstdDecompressor()


_CONTEXTS = _Contexts()


LATCHED_DEFLATE_LEVEL = 9
"""deflate level of latched messages (maps, robot descriptions): they are sent once per
change, not per period, so the best ratio is worth its time (benchmarks/media/map.py: the
1650 x 1650 map 83.5 KB at level 1, 37.9 KB at level 9 in ~90 ms)."""


def compress(
    frame: bytes,
    *,
    codec: CompressionCodec,
    topic: str,
    no_drop: bool,
    frame_codec: Codec | None = None,
    level: int | None = None,
) -> bytes:
    """Compress a whole frame into a Compressed frame, if that saves enough.

    Args:
        frame: The original frame (with its own metadata).
        codec: The compression codec.
        topic: Topic of the Compressed frame; must be the original frame's topic
            (receivers refuse a Compressed frame whose content is on another topic).
        no_drop: Copied into the Compressed frame's metadata, as ``fragments.split`` does
            (the original's publish time, seq and latched flag are copied from it).
        frame_codec: FlatBuffers codec to encode with (default: :func:`default_codec`).
        level: The codec's level; None: :data:`ZSTD_LEVEL` / :data:`DEFLATE_LEVEL` (made
            for streams). Latched messages, sent once, use :data:`LATCHED_DEFLATE_LEVEL`.

    Returns:
        The Compressed frame, or *frame* itself when it would not be at least
        :data:`MIN_SAVING` smaller.

    Raises:
        WireError: *frame* has no readable metadata, is already compressed or a fragment
            (compress before fragmenting), is on another topic, or is 4 GiB or more.
    """
    meta = read_metadata(frame)
    if meta.type in (COMPRESSED_TYPE, FRAGMENT_TYPE):
        raise WireError(f"cannot compress a {meta.type} frame: compress the original frame")
    if meta.topic != topic:
        raise WireError(f"the frame is on {meta.topic!r}, not on {topic!r}")
    if len(frame) > _U32_MAX:
        raise WireError(f"frame of {len(frame)} bytes is too large to compress")
    limit = len(frame) * (1.0 - MIN_SAVING)
    packed = _pack(codec, frame, level)
    if len(packed) > limit:  # cheap rejection before building the frame
        return frame
    frame_codec = frame_codec or default_codec()
    cls = frame_codec.registry.get(COMPRESSED_TYPE).cls
    msg = cls(int(codec), len(frame), np.frombuffer(packed, dtype=np.uint8))
    out = frame_codec.encode(msg, COMPRESSED_TYPE, topic, no_drop=no_drop,
                             publish_time_ns=meta.publish_time_ns, seq=meta.seq,
                             latched=meta.latched)
    # The Compressed table's own header (~100-200 bytes) decides for small frames.
    return out if len(out) <= limit else frame


def _pack(codec: CompressionCodec, frame: bytes, level: int | None = None) -> bytes:
    if codec == CompressionCodec.ZSTD:
        # One zstd frame with its content size in the header (receivers check it).
        if level is not None:
            return zstandard.ZstdCompressor(level=level).compress(frame)
        return _CONTEXTS.compressor.compress(frame)
    if codec == CompressionCodec.DEFLATE:
        # The stdlib has no reusable deflate context (a stream ends with its flush); setting
        # one up costs microseconds, next to milliseconds of deflating.
        return zlib.compress(frame, DEFLATE_LEVEL if level is None else level, wbits=-15)
    raise WireError(f"unknown compression codec {codec!r}")


def decompress(frame: bytes, max_bytes: int, *, frame_codec: Codec | None = None) -> bytes:
    """The original frame of a Compressed frame; any other frame is returned unchanged.

    Args:
        frame: A complete (reassembled) frame.
        max_bytes: Largest original frame accepted, bytes; nothing larger is allocated.
        frame_codec: FlatBuffers codec to decode with (default: :func:`default_codec`).

    Raises:
        WireError: *frame* has no readable metadata; or it is a Compressed frame that is
            malformed, uses an unknown codec, declares more than *max_bytes*, holds corrupt
            or trailing data, decompresses to another size than declared, or holds
            something other than one frame on its own topic.
    """
    meta = read_metadata(frame)
    if meta.type != COMPRESSED_TYPE:
        return frame
    _meta, msg = (frame_codec or default_codec()).decode_as(frame, COMPRESSED_TYPE)
    original = int(msg.original_bytes)
    where = f"Compressed frame on {meta.topic}"
    if original > max_bytes:
        raise WireError(f"{where} declares {original} bytes, over the limit of {max_bytes}")
    if original < _MIN_FRAME_BYTES:
        raise WireError(f"{where} declares {original} bytes: too short for a frame")
    if msg.codec == CompressionCodec.ZSTD:
        out = _unzstd(memoryview(msg.payload), original, where)
    elif msg.codec == CompressionCodec.DEFLATE:
        out = _inflate(memoryview(msg.payload), original, where)
    else:
        raise WireError(f"{where} uses unknown codec {int(msg.codec)} (1 zstd, 2 deflate)")
    if len(out) != original:
        raise WireError(f"{where} holds {len(out)} bytes, not the declared {original}")
    _check_inner(out, meta.topic, where)
    return out


def _unzstd(data: memoryview, original: int, where: str) -> bytes:
    try:
        # decompress() allocates the size the zstd header declares, whatever
        # max_output_size says: check it first, so a hostile header cannot allocate 4 GiB.
        declared = zstandard.frame_content_size(data)
    except zstandard.ZstdError as exc:
        raise WireError(f"{where}: corrupt zstd data: {exc}") from exc
    if declared not in (-1, original):
        raise WireError(f"{where}: zstd data declares {declared} bytes, not {original}")
    try:
        out: bytes = _CONTEXTS.decompressor.decompress(
            data, max_output_size=original, allow_extra_data=False)
    except zstandard.ZstdError as exc:
        raise WireError(f"{where}: corrupt zstd data or not {original} bytes: {exc}") from exc
    return out


def _inflate(data: memoryview, original: int, where: str) -> bytes:
    inflater = zlib.decompressobj(wbits=-15)
    try:
        out = inflater.decompress(data, original)  # max_length: never more than declared
        # Full but not at the end: one more byte means it inflates past original_bytes;
        # none means the end-of-stream marker just had not been read yet.
        full = len(out) == original and not inflater.eof
        if full and inflater.decompress(inflater.unconsumed_tail, 1):
            raise WireError(f"{where}: deflate data inflates past {original} bytes")
    except zlib.error as exc:
        raise WireError(f"{where}: corrupt deflate data: {exc}") from exc
    if not inflater.eof:
        raise WireError(f"{where}: truncated deflate data")
    if inflater.unused_data:
        raise WireError(f"{where}: {len(inflater.unused_data)} bytes after the deflate data")
    return out


def _check_inner(inner: bytes, topic: str, where: str) -> None:
    """The content must be one plain frame on the Compressed frame's own topic.

    The server checked the sender's permission on the outer topic only: a different inner
    topic would let a sender publish where it may not.
    """
    inner_meta = read_metadata(inner)
    if inner_meta.type in (COMPRESSED_TYPE, FRAGMENT_TYPE):
        raise WireError(f"{where} holds a {inner_meta.type} frame")
    if inner_meta.topic != topic:
        raise WireError(f"{where} holds a frame on another topic, {inner_meta.topic}")
