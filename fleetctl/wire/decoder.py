"""Generated FlatBuffers decoders, one per message type, built once from its layout.

Every read is bounds-checked against the frame, so a malformed or hostile frame raises
:class:`WireError`. Two properties keep hostile frames from costing more than honest ones:

- FlatBuffers offsets to strings, vectors and tables (``uoffset``) only point forward, and
  ROS types are not recursive, so decoding always terminates;
- offsets may be shared (many vector elements pointing at the same 1 MB vector), so each
  decode has a byte budget equal to the frame size: every table, string and vector read
  spends its size, as it would in a frame our encoder wrote (which never shares), and a
  frame that would cost more is rejected.

Arrays of numbers are read with one ``numpy.frombuffer(...).astype(...)`` copy.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from fleetctl.wire.encoder import struct_format
from fleetctl.wire.errors import WireError
from fleetctl.wire.layout import FieldKind, FieldLayout, MessageLayout
from fleetctl.wire.metadata import read_string, table_fields
from fleetctl.wire.registry import TypeRegistry

_U32 = struct.Struct("<I").unpack_from


class DecodeContext:
    """The frame being decoded and what is left of its byte budget."""

    __slots__ = ("budget", "buf", "n")

    def __init__(self, buf: bytes | memoryview) -> None:
        """Decode *buf* with a budget of its own size."""
        self.buf = buf
        self.n = len(buf)
        self.budget = self.n

    def spend(self, nbytes: int, what: str) -> None:
        """Charge *nbytes* to the budget.

        Raises:
            WireError: The frame references more bytes than it holds (shared offsets).
        """
        self.budget -= nbytes
        if self.budget < 0:
            raise WireError(f"malformed frame: {what} makes the frame reference more bytes "
                            f"than its {self.n}")

    def fail(self, what: str, pos: int) -> WireError:
        """A WireError naming *what* and where."""
        return WireError(f"malformed frame: {what} at byte {pos} of a {self.n}-byte frame")


TableDecoder = Callable[[DecodeContext, int], Any]
"""``decode(context, table_position) -> message``."""
_Read = Callable[[DecodeContext, int], Any]
_Default = Callable[[], Any]


class DecoderFactory:
    """Builds and caches one :data:`TableDecoder` (and default factory) per type."""

    def __init__(self, registry: TypeRegistry) -> None:
        """Decoders for the types of *registry*."""
        self._registry = registry
        self._tables: dict[str, TableDecoder] = {}
        self._defaults: dict[str, _Default] = {}

    def table(self, name: str) -> TableDecoder:
        """The decoder of type *name* stored as a table (raises WireError if unknown)."""
        dec = self._tables.get(name)
        if dec is None:
            layout = self._registry.get(name)
            dec = self._tables.get(layout.name) or self._make_table(layout)
            self._tables[name] = self._tables[layout.name] = dec
        return dec

    def default(self, name: str) -> _Default:
        """A factory of the all-defaults message of type *name* (for absent tables)."""
        make = self._defaults.get(name)
        if make is None:
            layout = self._registry.get(name)
            makers = [self._field_default(f) for f in layout.fields]
            cls = layout.cls

            def make_default() -> Any:
                return cls(*[m() for m in makers])

            make = self._defaults[name] = make_default
        return make

    def _make_table(self, layout: MessageLayout) -> TableDecoder:
        slot_count = layout.slot_count
        vtable_formats = [struct.Struct(f"<{k}H").unpack_from for k in range(slot_count + 1)]
        fields = [
            (f.slot, _width(f, self), self._reader(layout.name, f), self._field_default(f))
            for f in layout.fields
        ]
        cls, owner = layout.cls, layout.name

        def decode(ctx: DecodeContext, tpos: int) -> Any:
            ctx.spend(4, owner)
            buf = ctx.buf
            vt, vt_bytes, t_bytes = table_fields(buf, tpos, ctx.n)
            k = min(slot_count, (vt_bytes - 4) >> 1)
            offsets = vtable_formats[k](buf, vt + 4)
            end = tpos + t_bytes
            values = []
            for slot, width, read, default in fields:
                off = offsets[slot] if slot < k else 0
                if off == 0:
                    values.append(default())
                    continue
                pos = tpos + off
                if pos + width > end:
                    raise ctx.fail(f"{owner} field {slot} outside its table", pos)
                values.append(read(ctx, pos))
            return cls(*values)

        return decode

    def _field_default(self, f: FieldLayout) -> _Default:
        kind, fixed = f.kind, f.fixed_len or 0
        if kind is FieldKind.SCALAR:
            assert f.scalar is not None
            value = f.scalar.default
            return lambda: value
        if kind is FieldKind.STRING:
            return str
        if kind in (FieldKind.STRUCT, FieldKind.TABLE):
            assert f.ref is not None
            ref = f.ref
            return lambda: self.default(ref)()
        if kind is FieldKind.SCALAR_VECTOR:
            assert f.scalar is not None
            dtype = f.scalar.dtype
            return lambda: np.zeros(fixed, dtype=dtype)
        if kind is FieldKind.STRING_VECTOR:
            return lambda: [""] * fixed
        assert f.ref is not None
        ref = f.ref
        return lambda: [self.default(ref)() for _ in range(fixed)]

    def _reader(self, owner: str, f: FieldLayout) -> _Read:
        where = f"{owner}.{f.name}"
        kind = f.kind
        if kind is FieldKind.SCALAR:
            assert f.scalar is not None
            if f.scalar.ros == "bool":
                return lambda ctx, pos: ctx.buf[pos] != 0
            unpack = struct.Struct("<" + f.scalar.fmt).unpack_from
            return lambda ctx, pos: unpack(ctx.buf, pos)[0]
        if kind is FieldKind.STRUCT:
            assert f.ref is not None
            st, _align = struct_format(self._registry.get(f.ref))
            scls = self._registry.get(f.ref).cls
            return lambda ctx, pos: scls(*st.unpack_from(ctx.buf, pos))
        if kind is FieldKind.STRING:
            return _string_reader(where, f.bound)
        if kind is FieldKind.TABLE:
            assert f.ref is not None
            ref = f.ref

            def read_table(ctx: DecodeContext, pos: int) -> Any:
                return self.table(ref)(ctx, pos + _U32(ctx.buf, pos)[0])

            return read_table
        if kind is FieldKind.SCALAR_VECTOR:
            return _numbers_reader(where, f)
        if kind is FieldKind.STRUCT_VECTOR:
            return self._structs_reader(where, f)
        if kind is FieldKind.STRING_VECTOR:
            read_one = _string_reader(where, None)
        else:
            assert f.ref is not None
            ref = f.ref

            def read_one(ctx: DecodeContext, pos: int) -> Any:
                return self.table(ref)(ctx, pos + _U32(ctx.buf, pos)[0])

        def read_offsets(ctx: DecodeContext, pos: int) -> list[Any]:
            start, count = _vector(ctx, pos, 4, where, f)
            return [read_one(ctx, start + 4 * i) for i in range(count)]

        return read_offsets

    def _structs_reader(self, where: str, f: FieldLayout) -> _Read:
        assert f.ref is not None
        layout = self._registry.get(f.ref)
        st, _align = struct_format(layout)
        scls = layout.cls

        def read_structs(ctx: DecodeContext, pos: int) -> list[Any]:
            start, count = _vector(ctx, pos, st.size, where, f)
            data = bytes(ctx.buf[start : start + st.size * count])
            return [scls(*t) for t in st.iter_unpack(data)]

        return read_structs


def _width(f: FieldLayout, factory: DecoderFactory) -> int:
    """Bytes the field occupies inside its table."""
    if f.kind is FieldKind.SCALAR:
        assert f.scalar is not None
        return f.scalar.size_bytes
    if f.kind is FieldKind.STRUCT:
        assert f.ref is not None
        return struct_format(factory._registry.get(f.ref))[0].size
    return 4


def _vector(
    ctx: DecodeContext, pos: int, elem_bytes: int, where: str, f: FieldLayout
) -> tuple[int, int]:
    """Follow the vector offset at *pos*; return ``(first element position, count)``."""
    vpos = pos + _U32(ctx.buf, pos)[0]
    if vpos + 4 > ctx.n:
        raise ctx.fail(f"{where} vector outside the frame", vpos)
    count = _U32(ctx.buf, vpos)[0]
    nbytes = count * elem_bytes
    if vpos + 4 + nbytes > ctx.n:
        raise ctx.fail(f"{where} vector of {count} elements runs past the frame", vpos)
    if f.fixed_len is not None and count != f.fixed_len:
        raise WireError(f"{where}: fixed-size array of {f.fixed_len} has {count} elements")
    if f.bound is not None and count > f.bound:
        raise WireError(f"{where}: {count} elements exceed the bound {f.bound}")
    ctx.spend(4 + nbytes, where)
    return vpos + 4, count


def _numbers_reader(where: str, f: FieldLayout) -> _Read:
    assert f.scalar is not None
    dtype, size = f.scalar.dtype, f.scalar.size_bytes
    if f.scalar.ros == "bool":
        # Any nonzero byte is true; a raw numpy view would make bools that are neither.
        def read_bools(ctx: DecodeContext, pos: int) -> np.ndarray[Any, Any]:
            start, count = _vector(ctx, pos, size, where, f)
            flags: np.ndarray[Any, Any] = np.frombuffer(ctx.buf, np.uint8, count, start) != 0
            return flags

        return read_bools
    wire_dtype = dtype.newbyteorder("<")

    def read_numbers(ctx: DecodeContext, pos: int) -> np.ndarray[Any, Any]:
        start, count = _vector(ctx, pos, size, where, f)
        view = np.frombuffer(ctx.buf, dtype=wire_dtype, count=count, offset=start)
        return view.astype(dtype, copy=True)

    return read_numbers


def _string_reader(where: str, bound: int | None) -> _Read:
    def read(ctx: DecodeContext, pos: int) -> str:
        text = read_string(ctx.buf, pos, ctx.n, where)
        ctx.spend(4 + len(text), where)
        if bound is not None and len(text.encode("utf-8")) > bound:
            raise WireError(f"{where}: string exceeds its bound of {bound} bytes")
        return text

    return read
