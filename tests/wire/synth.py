"""Synthetic messages of any registered type, generated from the layout (test helper).

Values are random but deterministic per seed and exercise the edges: empty and non-empty
vectors, non-ASCII strings, extreme integers, and bounded/fixed lengths.
"""

from __future__ import annotations

import random
from typing import Any

import numpy as np

from fleetctl.wire.layout import FieldKind, FieldLayout, Scalar
from fleetctl.wire.registry import TypeRegistry

_TEXT = "abcXYZ019 _/-.:éü中文🤖"


def scalar_value(rng: random.Random, scalar: Scalar) -> Any:
    """One random value of a base type (exactly representable in it)."""
    if scalar.ros == "bool":
        return rng.random() < 0.5
    if scalar.fmt in "fd":
        value = rng.choice([0.0, -1.5, 3.25, rng.uniform(-1e6, 1e6)])
        return float(np.float32(value)) if scalar.fmt == "f" else value
    info = np.iinfo(scalar.dtype)
    return rng.choice([0, int(info.min), int(info.max), rng.randint(int(info.min), int(info.max))])


def text(rng: random.Random, max_chars: int = 12) -> str:
    """A random string with non-ASCII characters."""
    return "".join(rng.choice(_TEXT) for _ in range(rng.randint(0, max_chars)))


def _count(rng: random.Random, f: FieldLayout, max_len: int) -> int:
    if f.fixed_len is not None:
        return f.fixed_len
    top = max_len if f.bound is None else min(max_len, f.bound)
    return rng.randint(0, top)


def _field_value(registry: TypeRegistry, f: FieldLayout, rng: random.Random, max_len: int) -> Any:
    kind = f.kind
    if kind is FieldKind.SCALAR:
        assert f.scalar is not None
        return scalar_value(rng, f.scalar)
    if kind is FieldKind.STRING:
        value = text(rng)
        while f.bound is not None and len(value.encode()) > f.bound:
            value = value[:-1]
        return value
    if kind in (FieldKind.STRUCT, FieldKind.TABLE):
        assert f.ref is not None
        return message(registry, f.ref, rng, max_len)
    count = _count(rng, f, max_len)
    if kind is FieldKind.SCALAR_VECTOR:
        assert f.scalar is not None
        return np.array([scalar_value(rng, f.scalar) for _ in range(count)], dtype=f.scalar.dtype)
    if kind is FieldKind.STRING_VECTOR:
        return [text(rng) for _ in range(count)]
    assert f.ref is not None
    return [message(registry, f.ref, rng, max(0, max_len - 2)) for _ in range(count)]


def message(registry: TypeRegistry, name: str, rng: random.Random, max_len: int = 4) -> Any:
    """A random message of type *name*; vectors have at most *max_len* elements."""
    layout = registry.get(name)
    return layout.cls(*[_field_value(registry, f, rng, max_len) for f in layout.fields])
