"""Encode ROS messages to Robofleet-style FlatBuffer frames and back.

A frame is one FlatBuffer whose root table has ``__metadata`` in field 0 and the ROS
fields after it (``docs/design.md`` section 1). Messages are rosbags message objects, so
``registry.typestore.serialize_cdr`` / ``deserialize_cdr`` convert them to and from CDR;
any object with the same attribute names encodes as well.
"""

from __future__ import annotations

import struct
from functools import lru_cache
from typing import Any

import flatbuffers
import numpy as np

from fleetctl.wire.builder import LeanBuilder
from fleetctl.wire.decoder import DecodeContext, DecoderFactory
from fleetctl.wire.encoder import EncoderFactory
from fleetctl.wire.errors import WireError
from fleetctl.wire.metadata import METADATA_TYPE, Metadata, normalize_type, read_root
from fleetctl.wire.registry import TypeRegistry

_MIN_BUILDER_BYTES = 256
_MAX_HINT_BYTES = 64 << 20
# From this size a builder starts on uninitialized memory instead of bytearray's zeroes.
_UNINITIALIZED_FROM_BYTES = 64 * 1024
# Anything else a decoder could raise on input its checks missed is still a bad frame.
_DECODE_ERRORS = (struct.error, IndexError, ValueError, TypeError, OverflowError, RecursionError)


def new_builder(size: int) -> flatbuffers.Builder:
    """A FlatBuffers builder (:class:`LeanBuilder`: the library's bytes, fewer calls) with
    room for *size* bytes before it has to grow.

    Large buffers start uninitialized: ``bytearray(size)`` zeroes all of it first, a pass
    over a megabyte per point cloud that nothing reads. The builder writes every byte it
    emits, alignment padding included (``Builder.Pad``), as the C++ builder does on its
    uninitialized ``vector_downward``; ``tests/wire/test_codec.py`` encodes every fixture
    on a buffer filled with garbage to hold it to that.
    """
    if size < _UNINITIALIZED_FROM_BYTES:
        return LeanBuilder(size)
    builder = LeanBuilder(0)
    builder.Bytes = np.empty(size, dtype=np.uint8).data
    builder.head = size
    return builder


class Codec:
    """Encoder and decoder of frames for the types of one :class:`TypeRegistry`.

    Encoders and decoders are generated per type on first use and cached.
    """

    def __init__(self, registry: TypeRegistry) -> None:
        """A codec for the types *registry* knows (now or later)."""
        self.registry = registry
        self._encoders = EncoderFactory(registry)
        self._decoders = DecoderFactory(registry)
        self._meta_cls = registry.get(METADATA_TYPE).cls
        self._size_hint: dict[str, int] = {}

    def encode(
        self,
        msg: Any,
        type_name: str,
        topic: str,
        *,
        no_drop: bool = False,
        publish_time_ns: int = 0,
        seq: int = 0,
        latched: bool = False,
    ) -> bytes:
        """Encode one message as a frame (``bytes`` copy of :meth:`encode_view`'s result).

        Args:
            msg: A rosbags message object of *type_name* (or any object with its fields).
            type_name: Message type in any accepted form; written in ROS 2 form.
            topic: Topic the frame is published on.
            no_drop: Ask for reliable, in-order delivery.
            publish_time_ns: Wall clock in ns since the epoch when the robot got it.
            seq: Per-topic sequence number of the sender.
            latched: Mark the message latched (the server keeps the last one per sender
                and topic for later subscribers).

        Returns:
            The frame (one WebSocket binary message).

        Raises:
            WireError: Unknown type, or *msg* does not fit it (the message names the field).
        """
        return bytes(self.encode_view(msg, type_name, topic, no_drop=no_drop,
                                      publish_time_ns=publish_time_ns, seq=seq,
                                      latched=latched))

    def encode_view(
        self,
        msg: Any,
        type_name: str,
        topic: str,
        *,
        no_drop: bool = False,
        publish_time_ns: int = 0,
        seq: int = 0,
        latched: bool = False,
    ) -> memoryview:
        """Like :meth:`encode`, but the frame is a read-only view of the builder's buffer.

        Saves one copy of the frame (a cold pass over 1 MB per point cloud on the robot's
        send path). The buffer belongs to this call alone, so the view stays valid and
        unchanged; the buffer behind it is somewhat larger than the frame (the size
        hint's headroom), which the view keeps alive.
        """
        name = normalize_type(type_name)
        if name == METADATA_TYPE:
            raise WireError(f"{METADATA_TYPE} is the frame header, not a message type")
        encode_table = self._encoders.table(name)
        builder = new_builder(self._size_hint.get(name, _MIN_BUILDER_BYTES))
        meta = self._meta_cls(name, topic, bool(no_drop), publish_time_ns, seq, bool(latched))
        meta_off = self._encoders.table(METADATA_TYPE)(builder, meta, 0)
        root = encode_table(builder, msg, meta_off)
        builder.Finish(root)
        frame = memoryview(builder.Bytes)[builder.Head() :].toreadonly()
        # Start the next builder of this type big enough to never grow (each growth copies).
        self._size_hint[name] = min(_MAX_HINT_BYTES, len(frame) + len(frame) // 8 + 64)
        return frame

    def decode(self, frame: bytes | memoryview) -> tuple[Metadata, Any]:
        """Decode a frame.

        Returns:
            The metadata and the message (a rosbags message object of ``metadata.type``).

        Raises:
            WireError: The frame is malformed, truncated or of an unknown type.
        """
        metadata, root = read_root(frame)
        if metadata.type == METADATA_TYPE:
            raise WireError(f"malformed frame: {METADATA_TYPE} is not a message type")
        decode_table = self._decoders.table(metadata.type)
        return metadata, _guarded(decode_table, DecodeContext(frame), root, metadata.type)

    def decode_as(self, frame: bytes | memoryview, type_name: str) -> tuple[Metadata, Any]:
        """Decode a frame that must be of type *type_name*.

        Raises:
            WireError: The frame is malformed or of another type.
        """
        expected = normalize_type(type_name)
        metadata, root = read_root(frame)
        if metadata.type != expected:
            raise WireError(f"expected a {expected} frame, got {metadata.type}")
        decode_table = self._decoders.table(expected)
        return metadata, _guarded(decode_table, DecodeContext(frame), root, expected)

    def decode_table(self, frame: bytes | memoryview, type_name: str, table_pos: int) -> Any:
        """Decode the table of *type_name* at *table_pos* (for tests and tools).

        Raises:
            WireError: The table is malformed.
        """
        decode_table = self._decoders.table(type_name)
        return _guarded(decode_table, DecodeContext(frame), table_pos, type_name)


def _guarded(decode_table: Any, ctx: DecodeContext, pos: int, type_name: str) -> Any:
    try:
        return decode_table(ctx, pos)
    except WireError:
        raise
    except _DECODE_ERRORS as exc:
        raise WireError(f"malformed {type_name} frame: {exc}") from exc


@lru_cache(maxsize=1)
def default_codec() -> Codec:
    """A process-wide codec over :meth:`TypeRegistry.default` (built on first use)."""
    return Codec(TypeRegistry.default())
