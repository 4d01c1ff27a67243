"""Frame metadata: the ``__metadata`` table every root table carries in field 0.

:func:`read_metadata` is the hot path of the relay server (it runs on every frame), so it
is written by hand against the FlatBuffers binary layout instead of going through the
generic codec; ``tests/wire/test_metadata.py`` cross-checks it against the codec. Every
read is bounds-checked: a hostile buffer raises :class:`WireError` and nothing else.

Binary layout (FlatBuffers, little endian): ``u32`` root offset at byte 0 -> table; a table
starts with an ``i32`` that points back to its vtable (``vtable = table - value``); the vtable
is ``u16 vtable_bytes, u16 table_bytes, u16 field_offset[...]`` where 0 means absent.
"""

from __future__ import annotations

import re
import struct
from functools import lru_cache
from typing import NamedTuple

from fleetctl.wire.errors import WireError

METADATA_TYPE = "fleetctl_msgs/msg/MsgMetadata"
"""ROS-style name of the metadata table (its fields are described by shipped .msg text)."""

_U32 = struct.Struct("<I").unpack_from
_I32 = struct.Struct("<i").unpack_from
_U16X2 = struct.Struct("<HH").unpack_from
_U64 = struct.Struct("<Q").unpack_from

# Bare names Robofleet puts on the wire for its control messages.
_BARE_NAMES = {
    "RobofleetSubscription": "amrl_msgs/msg/RobofleetSubscription",
    "RobofleetStatus": "amrl_msgs/msg/RobofleetStatus",
}
_NAME_RE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)/(?:msg/)?([A-Za-z][A-Za-z0-9_]*)")
_MAX_TYPE_NAME_CHARS = 256


class Metadata(NamedTuple):
    """The metadata of one frame (a NamedTuple: immutable, and built on every relayed frame
    ten times faster than a frozen dataclass).

    Attributes:
        type: ROS 2 type name, normalized (``sensor_msgs/msg/LaserScan``).
        topic: Topic the message is published on (``/husky1/scan``).
        no_drop: The sender asks for reliable, in-order delivery.
        publish_time_ns: Wall clock in ns since the epoch when the robot took the message
            from ROS; 0 when the sender did not say.
        seq: Per-topic sequence number of the sender; 0 when the sender did not say.
        latched: The message is latched (its ROS publisher is ``TRANSIENT_LOCAL``): the
            server keeps the last one per (sender, topic) for later subscribers. Frames
            written before this field existed read as False.
    """

    type: str
    topic: str
    no_drop: bool = False
    publish_time_ns: int = 0
    seq: int = 0
    latched: bool = False


@lru_cache(maxsize=4096)
def normalize_type(name: str) -> str:
    """Return the ROS 2 form ``pkg/msg/Name`` of a message type name.

    Accepts ``pkg/msg/Name``, the ROS 1 form ``pkg/Name`` and the bare Robofleet control
    names ``RobofleetSubscription`` / ``RobofleetStatus``.

    Raises:
        WireError: The name has none of those forms.
    """
    bare = _BARE_NAMES.get(name)
    if bare is not None:
        return bare
    match = _NAME_RE.fullmatch(name) if len(name) <= _MAX_TYPE_NAME_CHARS else None
    if match is None:
        raise WireError(f"bad message type name {name[:80]!r}: expected pkg/msg/Name")
    return f"{match.group(1)}/msg/{match.group(2)}"


def _fail(what: str, pos: int, size: int) -> WireError:
    return WireError(f"malformed frame: {what} at byte {pos} of a {size}-byte frame")


def table_fields(frame: bytes | memoryview, tpos: int, n: int) -> tuple[int, int, int]:
    """Validate the table at *tpos*; return ``(vtable_pos, vtable_bytes, table_bytes)``.

    Raises:
        WireError: The table or its vtable lies (partly) outside the frame.
    """
    if tpos < 0 or tpos + 4 > n:
        raise _fail("table outside the frame", tpos, n)
    vt = tpos - _I32(frame, tpos)[0]
    if vt < 0 or vt + 4 > n:
        raise _fail("vtable outside the frame", vt, n)
    vt_bytes, t_bytes = _U16X2(frame, vt)
    if vt_bytes < 4 or vt_bytes & 1 or vt + vt_bytes > n or t_bytes < 4 or tpos + t_bytes > n:
        raise _fail("table or vtable size outside the frame", vt, n)
    return vt, vt_bytes, t_bytes


def field_pos(frame: bytes | memoryview, tpos: int, vt: int, vt_bytes: int, slot: int) -> int:
    """Absolute position of field *slot* of a validated table, or 0 when it is absent."""
    entry = 4 + 2 * slot
    if entry + 2 > vt_bytes:
        return 0
    off: int = struct.unpack_from("<H", frame, vt + entry)[0]
    return tpos + off if off else 0


def read_string(frame: bytes | memoryview, fpos: int, n: int, what: str) -> str:
    """Read the string whose offset is at *fpos* (bounds- and UTF-8-checked).

    Raises:
        WireError: The string lies outside the frame, lacks its NUL or is not UTF-8;
            the message names *what*.
    """
    if fpos + 4 > n:
        raise _fail(f"{what} offset outside the frame", fpos, n)
    spos = fpos + _U32(frame, fpos)[0]
    if spos + 4 > n:
        raise _fail(f"{what} outside the frame", spos, n)
    length = _U32(frame, spos)[0]
    end = spos + 4 + length
    if end + 1 > n or frame[end] != 0:
        raise _fail(f"{what} of {length} bytes runs past the frame or lacks its NUL", spos, n)
    try:
        return bytes(frame[spos + 4 : end]).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise _fail(f"{what} is not UTF-8", spos, n) from exc


# MsgMetadata's fields: type, topic, no_drop, publish_time_ns, seq, latched (vtable slots).
_META_FIELDS = 6
_VTABLE_ENTRIES = [struct.Struct(f"<{k}H").unpack_from for k in range(_META_FIELDS + 1)]
_TYPE_CACHE: dict[bytes, str] = {}
_TYPE_CACHE_MAX = 1024


def read_root(frame: bytes | memoryview) -> tuple[Metadata, int]:
    """Read the metadata of *frame*; return it and the position of the root table.

    The relay runs this on every frame, so it is one flat function (each Python call and
    ``unpack_from`` costs ~0.1 us, and this was half the relay's time per small frame);
    every read is still bounds-checked as in :func:`table_fields` and :func:`read_string`.

    Raises:
        WireError: The frame is truncated or malformed, has no ``__metadata``, or its type
            name is malformed.
    """
    n = len(frame)
    if n < 8:
        raise WireError(f"malformed frame: {n} bytes is too short for a FlatBuffer")
    root = _U32(frame, 0)[0]
    vt, vt_bytes, t_bytes = table_fields(frame, root, n)
    moff = _U16X2(frame, vt + 4)[0] if vt_bytes >= 6 else 0
    if not moff:
        raise WireError("malformed frame: the root table has no __metadata (field 0)")
    mpos = root + moff
    if moff + 4 > t_bytes:
        raise _fail("__metadata offset outside its table", mpos, n)
    mtab = mpos + _U32(frame, mpos)[0]
    vt, vt_bytes, t_bytes = table_fields(frame, mtab, n)
    k = (vt_bytes - 4) >> 1
    # A shorter vtable (an older or Robofleet writer) leaves the later fields absent; a
    # longer one (a newer writer) has fields this reader ignores.
    if k >= _META_FIELDS:
        o_type, o_topic, o_drop, o_time, o_seq, o_latched = _VTABLE_ENTRIES[_META_FIELDS](
            frame, vt + 4)
    else:
        o_type, o_topic, o_drop, o_time, o_seq, o_latched = (
            _VTABLE_ENTRIES[k](frame, vt + 4) + (0,) * (_META_FIELDS - k))
    if not o_type or not o_topic:
        raise WireError("malformed frame: __metadata has no type or no topic")
    if (o_type + 4 > t_bytes or o_topic + 4 > t_bytes or o_drop + 1 > t_bytes
            or o_time + 8 > t_bytes or o_seq + 8 > t_bytes or o_latched + 1 > t_bytes):
        raise _fail("__metadata field outside its table", mtab, n)
    # The topic string, inline (read_string is the reference for these checks).
    fpos = mtab + o_topic
    spos = fpos + _U32(frame, fpos)[0]
    if spos + 4 > n:
        raise _fail("__metadata.topic outside the frame", spos, n)
    end = spos + 4 + _U32(frame, spos)[0]
    if end + 1 > n or frame[end] != 0:
        raise _fail("__metadata.topic runs past the frame or lacks its NUL", spos, n)
    if end == spos + 4:
        raise WireError("malformed frame: __metadata.topic is empty")
    try:
        topic = str(frame[spos + 4 : end], "utf-8")
    except UnicodeDecodeError as exc:
        raise _fail("__metadata.topic is not UTF-8", spos, n) from exc
    return Metadata(
        _read_type(frame, mtab + o_type, n),
        topic,
        bool(o_drop and frame[mtab + o_drop]),
        _U64(frame, mtab + o_time)[0] if o_time else 0,
        _U64(frame, mtab + o_seq)[0] if o_seq else 0,
        bool(o_latched and frame[mtab + o_latched]),
    ), root


def _read_type(frame: bytes | memoryview, fpos: int, n: int) -> str:
    """The normalized type name; a small cache skips decoding and normalizing repeats."""
    spos, end = fpos + _U32(frame, fpos)[0], -1
    if spos + 4 <= n:
        end = spos + 4 + _U32(frame, spos)[0]
        if end < n and frame[end] == 0:
            key = frame[spos + 4 : end]
            cached = _TYPE_CACHE.get(key if type(key) is bytes else bytes(key))
            if cached is not None:
                return cached
    name = normalize_type(read_string(frame, fpos, n, "__metadata.type"))
    if len(_TYPE_CACHE) >= _TYPE_CACHE_MAX:
        _TYPE_CACHE.clear()  # bounded: a peer sending many type names only costs the cache
    if end >= 0:  # read_string succeeded, so spos..end is the string's bytes
        _TYPE_CACHE[bytes(frame[spos + 4 : end])] = name
    return name


def read_metadata(frame: bytes | memoryview) -> Metadata:
    """Read the ``__metadata`` of a frame without decoding the rest.

    Every read is bounds-checked; the function never reads past the buffer and its cost
    does not depend on the size of the message.

    Args:
        frame: One WebSocket binary frame.

    Returns:
        The metadata, with the type name normalized to ROS 2 form.

    Raises:
        WireError: The frame is truncated or malformed, has no ``__metadata``, no type or
            topic, or its type name is malformed.
    """
    return read_root(frame)[0]
