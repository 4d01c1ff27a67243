"""Test helpers: build rosbags message objects of any type from partial dicts, and turn
decoded messages into JSON the JS decoder's output is compared with."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from fleetctl.wire.layout import FieldKind, FieldLayout
from fleetctl.wire.registry import TypeRegistry

_VECTORS = {
    FieldKind.SCALAR_VECTOR,
    FieldKind.STRING_VECTOR,
    FieldKind.STRUCT_VECTOR,
    FieldKind.TABLE_VECTOR,
}


def make(registry: TypeRegistry, type_name: str, values: dict[str, Any] | None = None) -> Any:
    """A message of *type_name* with *values* (nested dicts for nested messages), the
    remaining fields zero/empty."""
    layout = registry.get(type_name)
    values = values or {}
    kwargs = {f.name: _field(registry, f, values.get(f.name)) for f in layout.fields}
    unknown = set(values) - set(kwargs)
    if unknown:
        raise KeyError(f"{type_name} has no fields {sorted(unknown)}")
    return layout.cls(**kwargs)


def _field(registry: TypeRegistry, f: FieldLayout, v: Any) -> Any:
    if f.kind in _VECTORS:
        return _vector(registry, f, v)
    if f.kind in (FieldKind.STRUCT, FieldKind.TABLE):
        assert f.ref is not None
        return v if dataclasses.is_dataclass(v) else make(registry, f.ref, v)
    if f.kind is FieldKind.STRING:
        return v or ""
    assert f.scalar is not None
    return f.scalar.default if v is None else v


def _vector(registry: TypeRegistry, f: FieldLayout, v: Any) -> Any:
    n = f.fixed_len or 0
    if f.kind is FieldKind.SCALAR_VECTOR:
        assert f.scalar is not None
        return np.asarray(v if v is not None else np.zeros(n), dtype=f.scalar.dtype)
    if f.kind is FieldKind.STRING_VECTOR:
        return list(v or [""] * n)
    assert f.ref is not None
    items = v if v is not None else [None] * n
    return [x if dataclasses.is_dataclass(x) else make(registry, f.ref, x) for x in items]


def _is_ros_field(name: str) -> bool:
    # rosbags classes also carry __msgtype__ and the constants (UPPER_CASE; ROS field
    # names are lower case).
    return not name.startswith("__") and not name.isupper()


def to_json(value: Any) -> Any:
    """Canonical JSON of a decoded message: ints as strings (exact for 64-bit), floats as
    numbers (non-finite as their JS spelling), bools as bools."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: to_json(getattr(value, f.name))
            for f in dataclasses.fields(value)
            if _is_ros_field(f.name)
        }
    if isinstance(value, np.ndarray):
        return [to_json(x) for x in value.tolist()]
    if isinstance(value, list | tuple):
        return [to_json(x) for x in value]
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        x = float(value)
        if math.isnan(x):
            return "NaN"
        if math.isinf(x):
            return "Infinity" if x > 0 else "-Infinity"
        return x
    return value


def to_plain(value: Any) -> Any:
    """JSON of a message as the page's builder takes it: plain numbers and lists."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: to_plain(getattr(value, f.name))
            for f in dataclasses.fields(value)
            if _is_ros_field(f.name)
        }
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, list | tuple):
        return [to_plain(x) for x in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 2**53:
        return {"$bigint": str(value)}  # JSON numbers would lose the low bits
    return value
