"""The FlatBuffers table layout of a ROS message type, derived from its definition.

One :class:`MessageLayout` per type is the single source the codec, the ``.fbs`` exporter and
the JSON layout for the web page are generated from, so the three cannot disagree.

Mapping (see ``docs/wire.md``):

- every message is a table; vtable slot 0 is ``__metadata`` (set only on the root table),
  the ROS fields follow in declaration order from slot 1. The metadata table itself is the
  exception: its fields start at slot 0.
- ``builtin_interfaces/msg/Time`` and ``Duration`` are inline structs
  ``{sec: int32, nanosec: uint32}`` wherever they are a field or an array element; as a root
  type they are a table like any other message.
- sequences, bounded sequences and fixed-size arrays are vectors (FlatBuffers tables cannot
  hold fixed-size arrays); the fixed length and the bound are checked on both ends.
- ``byte`` is ``int8`` and ``char`` is ``uint8``, as in the rosbags type store.
- constants are not encoded.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

import numpy as np


class FieldKind(StrEnum):
    """How a field is stored in a table."""

    SCALAR = "scalar"
    STRING = "string"
    STRUCT = "struct"
    TABLE = "table"
    SCALAR_VECTOR = "scalar_vector"
    STRING_VECTOR = "string_vector"
    STRUCT_VECTOR = "struct_vector"
    TABLE_VECTOR = "table_vector"


@dataclass(frozen=True, slots=True)
class Scalar:
    """A ROS base type and its FlatBuffers representation.

    Attributes:
        ros: ROS base type name (``float32``).
        fbs: FlatBuffers schema type name (``float``).
        fmt: :mod:`struct` format character, little endian implied.
        size_bytes: Size of one value in bytes.
        dtype: numpy dtype of an array of this type, as the rosbags store uses it.
    """

    ros: str
    fbs: str
    fmt: str
    size_bytes: int
    dtype: np.dtype[Any]

    @property
    def default(self) -> bool | int | float:
        """The value of an absent field."""
        if self.ros == "bool":
            return False
        return 0.0 if self.fmt in "fd" else 0


def _scalar(ros: str, fbs: str, fmt: str, dtype: str) -> Scalar:
    return Scalar(ros, fbs, fmt, struct.calcsize("<" + fmt), np.dtype(dtype))


SCALARS: dict[str, Scalar] = {
    s.ros: s
    for s in (
        _scalar("bool", "bool", "B", "bool"),
        _scalar("byte", "byte", "b", "int8"),
        _scalar("char", "ubyte", "B", "uint8"),
        _scalar("int8", "byte", "b", "int8"),
        _scalar("uint8", "ubyte", "B", "uint8"),
        _scalar("int16", "short", "h", "int16"),
        _scalar("uint16", "ushort", "H", "uint16"),
        _scalar("int32", "int", "i", "int32"),
        _scalar("uint32", "uint", "I", "uint32"),
        _scalar("int64", "long", "q", "int64"),
        _scalar("uint64", "ulong", "Q", "uint64"),
        _scalar("float32", "float", "f", "float32"),
        _scalar("float64", "double", "d", "float64"),
    )
}
STRING_TYPES = frozenset({"string", "wstring"})
STRUCT_TYPES = frozenset({"builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration"})
"""Types stored inline as FlatBuffers structs when nested (design.md section 1)."""

# Field names the flatc-generated code of some language uses for itself; a ROS field with
# such a name gets a trailing underscore in the schema (the wire only carries slot numbers).
_RESERVED_FIELD_NAMES = frozenset({"init", "table", "struct", "union", "enum", "namespace"})


def fbs_field_name(ros_name: str) -> str:
    """The schema name of a ROS field (ROS names are kept unless flatc output would clash)."""
    return ros_name + "_" if ros_name in _RESERVED_FIELD_NAMES else ros_name


@dataclass(frozen=True, slots=True)
class FieldLayout:
    """One ROS field in a table.

    Attributes:
        name: ROS field name.
        fbs_name: Field name in the ``.fbs`` schema.
        slot: vtable slot index (0 is ``__metadata``).
        kind: How it is stored.
        scalar: Element base type for scalar kinds, else None.
        ref: Nested message type name for struct/table kinds, else None.
        fixed_len: Element count of a fixed-size array, else None.
        bound: Upper bound of a bounded sequence or string, else None.
    """

    name: str
    fbs_name: str
    slot: int
    kind: FieldKind
    scalar: Scalar | None = None
    ref: str | None = None
    fixed_len: int | None = None
    bound: int | None = None


@dataclass(frozen=True, slots=True)
class MessageLayout:
    """The table layout of one message type.

    Attributes:
        name: ROS 2 type name.
        cls: The rosbags message class (a dataclass; fields in declaration order).
        fields: The ROS fields, in declaration order.
        first_slot: Slot of the first ROS field: 1, or 0 for the metadata table.
        is_struct: Stored inline as a struct when nested (Time, Duration).
    """

    name: str
    cls: Any
    fields: tuple[FieldLayout, ...]
    first_slot: int
    is_struct: bool

    @property
    def slot_count(self) -> int:
        """Number of vtable slots of the table form."""
        return self.first_slot + len(self.fields)
