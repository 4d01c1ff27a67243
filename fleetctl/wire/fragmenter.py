"""Fast fragment splitting for the send path: same bytes as :func:`.fragments.split`.

Encoding each fragment through the generic codec costs ~100 us (a FlatBuffers builder per
fragment): 6.5 ms per 1 MB point cloud, 0.5 ms per 64 KB message, which alone would cap a
link at ~130 MB/s and eat a 10 Hz cloud's CPU budget. But the fragments of a stream have
few layouts: for a given *shape* (topic, no_drop, latched, fragment payload size, count,
last payload size, and which of message_id / seq / publish_time_ns are non-zero, because
FlatBuffers omits zero scalars) there are three: the first fragment (``index`` 0 is absent),
the middle ones and the last one. :class:`Fragmenter` encodes those three once per shape
with the codec and builds every fragment as a template copy with the scalars and payload
patched in place. ``tests/client/test_fragmenter.py`` checks the output is byte-identical
to ``split``.
"""

from __future__ import annotations

import math
import struct
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import (
    FRAGMENT_TYPE,
    fragment_overhead,
    fragment_payload_span,
    split,
)
from fleetctl.wire.metadata import field_pos, read_metadata, table_fields

_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_U32_MAX = 0xFFFFFFFF
# Field slots of fleetctl_msgs/msg/Fragment (slot 0 is __metadata) and of MsgMetadata.
_SLOT_META, _SLOT_ID, _SLOT_INDEX = 0, 1, 2
_META_SLOT_TIME, _META_SLOT_SEQ = 3, 4


@dataclass(frozen=True)
class _Template:
    """One encoded fragment split around its payload.

    ``slots`` locate message_id, publish_time_ns, seq and index as ``(part, position,
    format)``: part 0 is ``head``, 1 is ``tail``; position -1 means absent (zero).
    """

    head: bytes
    tail: bytes
    slots: tuple[tuple[int, int, struct.Struct], ...]


# (topic, no_drop, latched, chunk, count, last_len, has id, has time, has seq); the flags
# are constant per shape, so the templates carry them and need no patching.
_Shape = tuple[str, bool, bool, int, int, int, bool, bool, bool]


class Fragmenter:
    """Splits frames like ``split``, with per-shape templates (bounded LRU cache).

    Args:
        codec: Codec to encode templates with (default: :func:`default_codec`).
        max_shapes: Templates are kept for this many shapes (LRU).
    """

    def __init__(self, codec: Codec | None = None, max_shapes: int = 64) -> None:
        self._codec = codec or default_codec()
        self._cls = self._codec.registry.get(FRAGMENT_TYPE).cls
        self._max_shapes = max_shapes
        self._shapes: OrderedDict[
            _Shape, tuple[_Template, _Template | None, _Template]] = OrderedDict()
        self._overheads: dict[tuple[str, bool, bool, bool, bool, bool], int] = {}

    def split(self, frame: bytes, *, topic: str, message_id: int, max_fragment_bytes: int,
              no_drop: bool, payload_bytes: int | None = None) -> list[bytes]:
        """Same arguments, result and errors as :func:`fleetctl.wire.fragments.split`."""
        if len(frame) <= max_fragment_bytes:
            return [frame]
        meta = read_metadata(frame)
        chunk = (max_fragment_bytes - self._overhead(topic, no_drop, meta.latched,
                                                     meta.publish_time_ns, meta.seq, message_id)
                 if payload_bytes is None else payload_bytes)
        count = math.ceil(len(frame) / chunk) if chunk > 0 else 0
        if count < 2 or len(frame) > _U32_MAX or message_id > 2**64 - 1 or message_id < 0:
            # Short messages, and every error case, are the reference implementation's job.
            return split(frame, topic=topic, message_id=message_id,
                         max_fragment_bytes=max_fragment_bytes, no_drop=no_drop,
                         codec=self._codec, payload_bytes=payload_bytes)
        last_len = len(frame) - (count - 1) * chunk
        shape: _Shape = (topic, no_drop, meta.latched, chunk, count, last_len,
                         message_id != 0, meta.publish_time_ns != 0, meta.seq != 0)
        first, middle, last = self._templates(shape, frame, message_id, meta)
        view = memoryview(frame)
        out = []
        for i in range(count):
            t = first if i == 0 else last if i == count - 1 else middle
            assert t is not None
            size = last_len if i == count - 1 else chunk
            parts = (bytearray(t.head), bytearray(t.tail))
            values = (message_id, meta.publish_time_ns, meta.seq, i)
            for (part, pos, fmt), value in zip(t.slots, values, strict=True):
                if pos >= 0:
                    fmt.pack_into(parts[part], pos, value)
            # One copy of the payload: head, payload slice and tail joined.
            out.append(b"".join((parts[0], view[i * chunk:i * chunk + size], parts[1])))
        return out

    def _overhead(self, topic: str, no_drop: bool, latched: bool, time_ns: int, seq: int,
                  message_id: int) -> int:
        # Cached per key: the overhead depends only on which scalars are zero, not on
        # their values (FlatBuffers omits zero scalars).
        key = (topic, no_drop, latched, time_ns != 0, seq != 0, message_id != 0)
        overhead = self._overheads.get(key)
        if overhead is None:
            if len(self._overheads) >= 4 * self._max_shapes:
                self._overheads.clear()
            overhead = self._overheads[key] = fragment_overhead(
                self._codec, topic, no_drop=no_drop, message_id=message_id,
                publish_time_ns=time_ns, seq=seq, latched=latched)
        return overhead

    def _encode(self, topic: str, flags: tuple[bool, bool], time_ns: int, seq: int, index: int,
                count: int, total: int, payload: np.ndarray[Any, Any], message_id: int) -> bytes:
        no_drop, latched = flags
        return self._codec.encode(self._cls(message_id, index, count, total, payload),
                                  FRAGMENT_TYPE, topic, no_drop=no_drop,
                                  publish_time_ns=time_ns, seq=seq, latched=latched)

    def _templates(self, shape: _Shape, frame: bytes, message_id: int,
                   meta: Any) -> tuple[_Template, _Template | None, _Template]:
        cached = self._shapes.get(shape)
        if cached is not None:
            self._shapes.move_to_end(shape)
            return cached
        topic, no_drop, latched, chunk, count, last_len = shape[:6]
        data = np.frombuffer(frame, dtype=np.uint8)

        def make(index: int, size: int) -> _Template:
            start = index * chunk
            encoded = self._encode(topic, (no_drop, latched), meta.publish_time_ns, meta.seq,
                                   index, count, len(frame), data[start:start + size], message_id)
            return _locate(encoded, size)

        made = (make(0, chunk), make(1, chunk) if count > 2 else None,
                make(count - 1, last_len))
        self._shapes[shape] = made
        if len(self._shapes) > self._max_shapes:
            self._shapes.popitem(last=False)
        return made


def _locate(frame: bytes, payload_len: int) -> _Template:
    """Find the variable fields of an encoded fragment."""
    n = len(frame)
    root = _U32.unpack_from(frame, 0)[0]
    vt, vt_bytes, _ = table_fields(frame, root, n)
    meta_field = field_pos(frame, root, vt, vt_bytes, _SLOT_META)
    meta_pos = meta_field + _U32.unpack_from(frame, meta_field)[0]
    mvt, mvt_bytes, _ = table_fields(frame, meta_pos, n)
    payload_pos, end = fragment_payload_span(frame, root)
    if end - payload_pos != payload_len:
        raise WireError("fragment template: payload not where expected")

    def where(pos: int, fmt: struct.Struct) -> tuple[int, int, struct.Struct]:
        if pos == 0:
            return (0, -1, fmt)
        if pos + fmt.size <= payload_pos:
            return (0, pos, fmt)
        if pos >= end:
            return (1, pos - end, fmt)
        raise WireError("fragment template: a scalar overlaps the payload")

    return _Template(
        head=frame[:payload_pos],
        tail=frame[end:],
        slots=(where(field_pos(frame, root, vt, vt_bytes, _SLOT_ID), _U64),
               where(field_pos(frame, meta_pos, mvt, mvt_bytes, _META_SLOT_TIME), _U64),
               where(field_pos(frame, meta_pos, mvt, mvt_bytes, _META_SLOT_SEQ), _U64),
               where(field_pos(frame, root, vt, vt_bytes, _SLOT_INDEX), _U32)),
    )


_DEFAULT: Fragmenter | None = None


def fast_split(
    frame: bytes, *, topic: str, message_id: int, max_fragment_bytes: int, no_drop: bool,
    payload_bytes: int | None = None,
) -> list[bytes]:
    """:meth:`Fragmenter.split` on a process-wide instance (drop-in for ``split``)."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = Fragmenter()
    return _DEFAULT.split(frame, topic=topic, message_id=message_id,
                          max_fragment_bytes=max_fragment_bytes, no_drop=no_drop,
                          payload_bytes=payload_bytes)
