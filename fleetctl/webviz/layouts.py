"""``/types/<T>.json``: the FlatBuffer layout of a ROS type, as the page's decoder reads it.

The document is derived from :meth:`fleetctl.wire.registry.TypeRegistry.get`, the same
:class:`~fleetctl.wire.layout.MessageLayout` objects the Python codec encodes and decodes
with, so the page and the codec cannot disagree. Format (read by ``static/js/fb/layout.js``)::

    {"type": "sensor_msgs/msg/LaserScan",
     "tables":  {NAME: {"fields": [{"name", "slot", "kind", ...}]}},
     "structs": {NAME: {"size", "align", "fields": [{"name", "offset", "kind", "scalar"}]}}}

with field kinds ``scalar`` (+ ``scalar``), ``string``, ``table`` (+ ``table``), ``struct``
(+ ``struct``) and ``vector`` (+ ``element``, itself a kind object). The root table has
field 0 ``__metadata`` (table ``fleetctl_msgs/msg/MsgMetadata``).
"""

from __future__ import annotations

import json
from collections import OrderedDict
from threading import Lock
from typing import Any

from fleetctl.wire.errors import WireError
from fleetctl.wire.layout import FieldKind, FieldLayout, MessageLayout
from fleetctl.wire.metadata import METADATA_TYPE, normalize_type
from fleetctl.wire.registry import TypeRegistry

# ROS base type -> the JS decoder's scalar names (byte is int8 and char uint8, as in rosbags).
_JS_SCALAR = {"byte": "int8", "char": "uint8"}

_VECTOR_ELEMENT = {
    FieldKind.SCALAR_VECTOR: FieldKind.SCALAR,
    FieldKind.STRING_VECTOR: FieldKind.STRING,
    FieldKind.STRUCT_VECTOR: FieldKind.STRUCT,
    FieldKind.TABLE_VECTOR: FieldKind.TABLE,
}


class LayoutError(Exception):
    """No layout can be given for a requested type name (the message says why)."""


def _kind(kind: FieldKind, f: FieldLayout) -> dict[str, Any]:
    if kind in _VECTOR_ELEMENT:
        return {"kind": "vector", "element": _kind(_VECTOR_ELEMENT[kind], f)}
    if kind is FieldKind.SCALAR:
        assert f.scalar is not None
        return {"kind": "scalar", "scalar": _JS_SCALAR.get(f.scalar.ros, f.scalar.ros)}
    if kind is FieldKind.STRING:
        return {"kind": "string"}
    return {"kind": kind.value, kind.value: f.ref}


def _struct_doc(layout: MessageLayout) -> dict[str, Any]:
    fields, offset, align = [], 0, 1
    for f in layout.fields:
        assert f.scalar is not None  # the registry allows only scalars in structs
        size = f.scalar.size_bytes
        offset += -offset % size  # FlatBuffers struct members are naturally aligned
        kind = _kind(FieldKind.SCALAR, f)
        fields.append({"name": f.name, "offset": offset, **kind})
        offset += size
        align = max(align, size)
    return {"size": offset + (-offset % align), "align": align, "fields": fields}


def describe_for_web(registry: TypeRegistry, type_name: str) -> dict[str, Any]:
    """The layout document of one root type and every type it contains.

    Args:
        registry: The type registry the fleet's codec uses.
        type_name: ROS type name in any accepted form.

    Returns:
        The JSON-ready document described in the module docstring.

    Raises:
        LayoutError: the name is malformed or the type is unknown.
    """
    try:
        root = normalize_type(type_name)
        tables: dict[str, Any] = {}
        structs: dict[str, Any] = {}
        todo = [(root, False)]
        while todo:
            name, as_struct = todo.pop()
            if name in (structs if as_struct else tables):
                continue
            layout = registry.get(name)
            if as_struct:
                structs[name] = _struct_doc(layout)
                continue
            fields = [{"name": f.name, "slot": f.slot, **_kind(f.kind, f)} for f in layout.fields]
            tables[name] = {"fields": fields}
            todo += [
                (f.ref, f.kind in (FieldKind.STRUCT, FieldKind.STRUCT_VECTOR))
                for f in layout.fields
                if f.ref
            ]
        meta = {"name": "__metadata", "slot": 0, "kind": "table", "table": METADATA_TYPE}
        if root != METADATA_TYPE:
            tables[root]["fields"].insert(0, meta)
            tables.setdefault(METADATA_TYPE, {"fields": []})
            if not tables[METADATA_TYPE]["fields"]:
                m = registry.get(METADATA_TYPE)
                tables[METADATA_TYPE]["fields"] = [
                    {"name": f.name, "slot": f.slot, **_kind(f.kind, f)} for f in m.fields
                ]
    except WireError as exc:
        raise LayoutError(str(exc)) from exc
    return {"type": root, "tables": tables, "structs": structs}


class LayoutCache:
    """JSON bodies of layout documents, computed once per type (bounded LRU)."""

    def __init__(self, registry: TypeRegistry, max_types: int = 256) -> None:
        """Serve layouts of *registry*'s types, keeping at most *max_types* bodies."""
        self._registry = registry
        self._max_types = max_types
        self._bodies: OrderedDict[str, bytes] = OrderedDict()
        self._lock = Lock()  # the HTTP server answers from several threads

    def __call__(self, type_name: str) -> bytes:
        """The JSON body for *type_name*; raises LayoutError when unknown."""
        with self._lock:
            body = self._bodies.get(type_name)
            if body is None:
                doc = describe_for_web(self._registry, type_name)
                body = json.dumps(doc, separators=(",", ":")).encode()
                self._bodies[type_name] = body
                if len(self._bodies) > self._max_types:
                    self._bodies.popitem(last=False)
            self._bodies.move_to_end(type_name)
            return body
