"""Generated FlatBuffers encoders, one per message type, built once from its layout.

An encoder is a closure over the layout: no per-type hand-written code, and no per-message
inspection of the definition. Arrays of numbers go into the buffer as one byte copy.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import numpy as np
from flatbuffers import number_types as nt
from flatbuffers.builder import Builder

from fleetctl.wire.errors import WireError
from fleetctl.wire.layout import FieldKind, FieldLayout, MessageLayout, Scalar
from fleetctl.wire.registry import TypeRegistry

TableEncoder = Callable[[Builder, Any, int], int]
"""``encode(builder, msg, metadata_offset) -> table offset``; offset 0 means no metadata."""

_Prep = Callable[[Builder, Any], Any]
_Put = Callable[[Builder, Any], None]

_FLAGS: dict[str, Any] = {
    "bool": nt.BoolFlags,
    "byte": nt.Int8Flags,
    "char": nt.Uint8Flags,
    "int8": nt.Int8Flags,
    "uint8": nt.Uint8Flags,
    "int16": nt.Int16Flags,
    "uint16": nt.Uint16Flags,
    "int32": nt.Int32Flags,
    "uint32": nt.Uint32Flags,
    "int64": nt.Int64Flags,
    "uint64": nt.Uint64Flags,
    "float32": nt.Float32Flags,
    "float64": nt.Float64Flags,
}
# rosbags gives empty messages (std_msgs/Empty) this dummy uint8 field; rclpy does not.
_EMPTY_MESSAGE_FIELD = "structure_needs_at_least_one_member"
_CATCH = (AttributeError, TypeError, ValueError, OverflowError, struct.error, IndexError)


def struct_format(layout: MessageLayout) -> tuple[struct.Struct, int]:
    """The packed little-endian format and alignment of a struct type.

    Fields are naturally aligned and the size is padded to the largest alignment, as
    flatc lays out structs.
    """
    fmt, pos, align = "<", 0, 1
    for f in layout.fields:
        assert f.scalar is not None
        size = f.scalar.size_bytes
        pad = -pos % size
        fmt += "x" * pad + f.scalar.fmt
        pos += pad + size
        align = max(align, size)
    fmt += "x" * (-pos % align)
    return struct.Struct(fmt), align


def write_raw(builder: Builder, data: bytes | memoryview, align: int) -> None:
    """Prepend raw bytes, aligned to *align*, in one copy (no per-element work)."""
    size = len(data)
    builder.Prep(align, size)
    builder.head = builder.head - size
    builder.Bytes[builder.head : builder.head + size] = data


def create_numeric_vector(builder: Builder, array: np.ndarray[Any, Any], scalar: Scalar) -> int:
    """Write a 1-D numeric array as a FlatBuffers vector with a single buffer copy."""
    data = array.astype(scalar.dtype.newbyteorder("<"), copy=False)
    count = data.shape[0]
    builder.StartVector(scalar.size_bytes, count, scalar.size_bytes)
    write_raw(builder, np.ascontiguousarray(data).view(np.uint8).data, 1)
    return int(builder.EndVector())


def _as_array(value: Any, scalar: Scalar) -> np.ndarray[Any, Any]:
    if isinstance(value, bytes | bytearray | memoryview):
        return np.frombuffer(value, dtype=scalar.dtype)
    if isinstance(value, list) and value and isinstance(value[0], bytes):
        # rclpy represents byte[] as a list of 1-byte bytes objects.
        return np.frombuffer(b"".join(value), dtype=scalar.dtype)
    array = np.asarray(value, dtype=scalar.dtype)
    if array.ndim != 1:
        raise ValueError(f"expected a 1-D array, got shape {array.shape}")
    return array


def _check_len(field: FieldLayout, count: int) -> None:
    if field.fixed_len is not None and count != field.fixed_len:
        raise ValueError(f"fixed-size array needs {field.fixed_len} elements, got {count}")
    if field.bound is not None and count > field.bound:
        raise ValueError(f"bounded to {field.bound} elements, got {count}")


class EncoderFactory:
    """Builds and caches one :data:`TableEncoder` per type of a registry."""

    def __init__(self, registry: TypeRegistry) -> None:
        """Encoders for the types of *registry*."""
        self._registry = registry
        self._tables: dict[str, TableEncoder] = {}
        self._structs: dict[str, tuple[struct.Struct, int, tuple[str, ...]]] = {}

    def table(self, name: str) -> TableEncoder:
        """The encoder of type *name* as a table (raises WireError if unknown)."""
        enc = self._tables.get(name)
        if enc is None:
            layout = self._registry.get(name)
            enc = self._tables.get(layout.name)
            if enc is None:
                enc = self._make_table(layout)
            self._tables[name] = self._tables[layout.name] = enc
        return enc

    def _struct(self, name: str) -> tuple[struct.Struct, int, tuple[str, ...]]:
        found = self._structs.get(name)
        if found is None:
            layout = self._registry.get(name)
            fmt, align = struct_format(layout)
            found = (fmt, align, tuple(f.name for f in layout.fields))
            self._structs[name] = found
        return found

    def _make_table(self, layout: MessageLayout) -> TableEncoder:
        fields = [(f.name, *self._field(f)) for f in layout.fields]
        # Prepend the widest values first so the builder inserts no alignment padding.
        order = sorted(range(len(fields)), key=lambda i: -fields[i][3])
        slot_count = layout.slot_count
        owner = layout.name

        def encode(builder: Builder, msg: Any, metadata: int) -> int:
            prepared = []
            for name, prep, _put, _width in fields:
                try:
                    if name == _EMPTY_MESSAGE_FIELD:
                        value = getattr(msg, name, 0)
                    else:
                        value = getattr(msg, name)
                    prepared.append(prep(builder, value))
                except WireError as exc:
                    raise WireError(f"{owner}.{name}: {exc}") from None
                except _CATCH as exc:
                    raise WireError(f"cannot encode {owner}.{name}: {exc}") from None
            builder.StartObject(slot_count)
            if metadata:
                builder.PrependUOffsetTRelativeSlot(0, metadata, 0)
            for i in order:
                try:
                    fields[i][2](builder, prepared[i])
                except _CATCH as exc:
                    raise WireError(f"cannot encode {owner}.{fields[i][0]}: {exc}") from None
            return int(builder.EndObject())

        return encode

    def _field(self, f: FieldLayout) -> tuple[_Prep, _Put, int]:
        """``(prepare, put, width_bytes)`` for one field.

        ``prepare`` runs before the table is started (it writes strings, vectors and
        sub-tables, which FlatBuffers cannot nest inside an open table); ``put`` writes the
        slot itself.
        """
        slot = f.slot
        if f.kind is FieldKind.SCALAR:
            assert f.scalar is not None
            flags, default = _FLAGS[f.scalar.ros], f.scalar.default

            def put_scalar(b: Builder, x: Any) -> None:
                b.PrependSlot(flags, slot, x, default)

            prep = _byte_scalar if f.scalar.ros == "byte" else _identity
            return prep, put_scalar, f.scalar.size_bytes

        def put_offset(b: Builder, off: int) -> None:
            b.PrependUOffsetTRelativeSlot(slot, off, 0)

        if f.kind is FieldKind.STRUCT:
            assert f.ref is not None
            st, align, names = self._struct(f.ref)

            def put_struct(b: Builder, value: Any) -> None:
                write_raw(b, st.pack(*[getattr(value, n) for n in names]), align)
                b.PrependStructSlot(slot, b.Offset(), 0)

            return _identity, put_struct, st.size
        return self._offset_prep(f), put_offset, 4

    def _offset_prep(self, f: FieldLayout) -> _Prep:
        kind = f.kind
        if kind is FieldKind.STRING:
            bound = f.bound

            def prep_string(b: Builder, s: str) -> int:
                data = s.encode("utf-8")
                if bound is not None and len(data) > bound:
                    raise ValueError(f"string bounded to {bound} bytes, got {len(data)}")
                return int(b.CreateString(data))

            return prep_string
        if kind is FieldKind.TABLE:
            assert f.ref is not None
            sub_name = f.ref
            return lambda b, v: self.table(sub_name)(b, v, 0)
        if kind is FieldKind.SCALAR_VECTOR:
            scalar = f.scalar
            assert scalar is not None

            def prep_numbers(b: Builder, value: Any) -> int:
                array = _as_array(value, scalar)
                _check_len(f, array.shape[0])
                return create_numeric_vector(b, array, scalar)

            return prep_numbers
        if kind is FieldKind.STRUCT_VECTOR:
            assert f.ref is not None
            st, align, names = self._struct(f.ref)

            def prep_structs(b: Builder, items: Any) -> int:
                _check_len(f, len(items))
                data = b"".join([st.pack(*[getattr(v, n) for n in names]) for v in items])
                b.StartVector(st.size, len(items), align)
                write_raw(b, data, 1)
                return int(b.EndVector())

            return prep_structs
        make_element: Callable[[Builder, Any], int]
        if kind is FieldKind.STRING_VECTOR:
            make_element = _string_element
        elif kind is FieldKind.TABLE_VECTOR:
            assert f.ref is not None
            sub = f.ref
            make_element = lambda b, v: self.table(sub)(b, v, 0)  # noqa: E731
        else:
            raise WireError(f"unsupported field kind {kind}")

        def prep_offsets(b: Builder, items: Any) -> int:
            _check_len(f, len(items))
            offsets = [make_element(b, v) for v in items]
            b.StartVector(4, len(offsets), 4)
            for off in reversed(offsets):
                b.PrependUOffsetTRelative(off)
            return int(b.EndVector())

        return prep_offsets


def _string_element(b: Builder, s: str) -> int:
    return int(b.CreateString(s.encode("utf-8")))


def _identity(_b: Builder, value: Any) -> Any:
    return value


def _byte_scalar(_b: Builder, value: Any) -> Any:
    # rclpy represents a byte as a 1-byte bytes object; rosbags as an int8.
    if isinstance(value, bytes) and len(value) == 1:
        return struct.unpack("b", value)[0]
    return value
