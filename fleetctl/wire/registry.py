"""The message types the wire format knows, and their table layouts.

Definitions come from the rosbags ROS 2 Jazzy type store (no ROS needed), from ``.msg``
texts shipped in ``fleetctl/wire/msg/<pkg>/msg/`` (amrl_msgs control types and our own
protocol types), and on a robot from the ``.msg`` files of the installed ROS packages
(:meth:`TypeRegistry.from_rclpy`).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable
from importlib import resources
from pathlib import Path
from typing import Any

from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from fleetctl.wire.errors import WireError
from fleetctl.wire.layout import (
    SCALARS,
    STRING_TYPES,
    STRUCT_TYPES,
    FieldKind,
    FieldLayout,
    MessageLayout,
    fbs_field_name,
)
from fleetctl.wire.metadata import METADATA_TYPE, normalize_type

_FieldDesc = tuple[Any, Any]


class TypeRegistry:
    """Message definitions by ROS 2 type name, with cached table layouts.

    Attributes:
        typestore: The rosbags type store; its ``serialize_cdr`` / ``deserialize_cdr``
            convert the message objects the codec uses to and from ROS 2 CDR.
    """

    def __init__(self, typestore: Typestore) -> None:
        """Wrap *typestore* (use :meth:`default` for the usual set of types)."""
        self.typestore = typestore
        self._layouts: dict[str, MessageLayout] = {}
        self._building: set[str] = set()

    @classmethod
    def default(cls) -> TypeRegistry:
        """The rosbags ROS 2 Jazzy store plus the shipped amrl_msgs and fleetctl_msgs."""
        registry = cls(get_typestore(Stores.ROS2_JAZZY))
        registry.add_msg_texts(_shipped_msg_texts())
        return registry

    @classmethod
    def default_with(cls, msg_types: Iterable[tuple[str, str]]) -> TypeRegistry:
        """:meth:`default` plus a fleet's own types, ``(pkg/msg/Name, .msg text)`` pairs
        (server.yaml ``msg_types``, ``fleetctl webviz --fleet``).

        Raises:
            WireError: A definition does not parse, names a type nobody defines, or is of
                a type the default registry has already.
        """
        texts = dict(msg_types)
        registry = cls.default()
        for name in texts:
            if name in registry:
                raise WireError(f"{name} is a ROS 2 Jazzy or fleetctl type already")
        registry.add_msg_texts(texts)
        for name in texts:
            registry.get(name)  # every field's type must be defined somewhere
        return registry

    def add_msg_text(self, name: str, text: str) -> None:
        """Register one type from its ``.msg`` text.

        Args:
            name: Type name in any accepted form (``pkg/msg/Name`` or ``pkg/Name``).
            text: The ``.msg`` definition.

        Raises:
            WireError: The text does not parse, or the type exists with another definition.
        """
        self.add_msg_texts({normalize_type(name): text})

    def add_msg_texts(self, texts: dict[str, str]) -> None:
        """Register several types at once (they may refer to each other).

        Raises:
            WireError: A text does not parse, or a type exists with another definition.
        """
        parsed: dict[str, Any] = {}
        for name, text in texts.items():
            try:
                parsed.update(get_types_from_msg(text, normalize_type(name)))
            except WireError:
                raise
            except Exception as exc:  # rosbags raises several parser exception types
                raise WireError(f"cannot parse the .msg text of {name}: {exc}") from exc
        try:
            self.typestore.register(parsed)
        except Exception as exc:
            raise WireError(f"cannot register {sorted(texts)}: {exc}") from exc

    def from_rclpy(self, prefixes: Iterable[str] | None = None) -> list[str]:
        """Register the ``.msg`` definitions of the installed ROS packages.

        Looks in ``<prefix>/share/<pkg>/msg/*.msg`` for every prefix in
        ``AMENT_PREFIX_PATH`` and ``sys.prefix`` (where the ROS wheels put them). Types the
        registry already has are kept as they are.

        Args:
            prefixes: Install prefixes to search instead of the default ones.

        Returns:
            The names of the types that were added.

        Raises:
            WireError: A definition does not parse or depends on a type nobody defines.
        """
        texts: dict[str, str] = {}
        for msg_file in _installed_msg_files(prefixes):
            name = f"{msg_file.parent.parent.name}/msg/{msg_file.stem}"
            if name not in self.typestore.fielddefs and name not in texts:
                texts[name] = msg_file.read_text(encoding="utf-8")
        if texts:
            self.add_msg_texts(texts)
            for name in texts:
                self.get(name)  # every dependency must be defined somewhere
        return sorted(texts)

    def names(self) -> list[str]:
        """All known type names, sorted."""
        return sorted(self.typestore.fielddefs)

    def __contains__(self, name: object) -> bool:
        try:
            return isinstance(name, str) and normalize_type(name) in self.typestore.fielddefs
        except WireError:
            return False

    def get(self, name: str) -> MessageLayout:
        """The table layout of a type (computed once, then cached).

        Args:
            name: Type name in any accepted form.

        Raises:
            WireError: The type is unknown or its name is malformed.
        """
        layout = self._layouts.get(name)
        if layout is None:
            full = normalize_type(name)
            layout = self._layouts.get(full) or self._build(full)
            self._layouts[name] = self._layouts[full] = layout
        return layout

    def _build(self, name: str) -> MessageLayout:
        defs = self.typestore.fielddefs.get(name)
        if defs is None:
            raise WireError(f"unknown message type {name}")
        first = 0 if name == METADATA_TYPE else 1
        fields = tuple(
            _field_layout(name, fname, desc, first + i) for i, (fname, desc) in enumerate(defs[1])
        )
        is_struct = name in STRUCT_TYPES
        if is_struct and any(f.kind is not FieldKind.SCALAR for f in fields):
            raise WireError(f"struct type {name} may only have scalar fields")
        self._check_refs(name, fields)
        return MessageLayout(name, self.typestore.types[name], fields, first, is_struct)

    def _check_refs(self, name: str, fields: tuple[FieldLayout, ...]) -> None:
        """Resolve every nested type now, so a missing one fails here and names the field."""
        if name in self._building:
            raise WireError(f"{name} contains itself (recursive types cannot be encoded)")
        self._building.add(name)
        try:
            for f in fields:
                if f.ref is not None:
                    try:
                        self.get(f.ref)
                    except WireError as exc:
                        raise WireError(f"{name}.{f.name}: {exc}") from None
        finally:
            self._building.discard(name)


def _field_layout(owner: str, name: str, desc: _FieldDesc, slot: int) -> FieldLayout:
    node, payload = desc
    fbs = fbs_field_name(name)
    if node == Nodetype.BASE:
        base, bound = payload
        if base in STRING_TYPES:
            return FieldLayout(name, fbs, slot, FieldKind.STRING, bound=bound or None)
        return FieldLayout(name, fbs, slot, FieldKind.SCALAR, scalar=_scalar(owner, name, base))
    if node == Nodetype.NAME:
        kind = FieldKind.STRUCT if payload in STRUCT_TYPES else FieldKind.TABLE
        return FieldLayout(name, fbs, slot, kind, ref=payload)
    if node in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        (sub_node, sub_payload), count = payload
        fixed = count if node == Nodetype.ARRAY else None
        bound = count or None if node == Nodetype.SEQUENCE else None
        if sub_node == Nodetype.NAME:
            struct_elements = sub_payload in STRUCT_TYPES
            kind = FieldKind.STRUCT_VECTOR if struct_elements else FieldKind.TABLE_VECTOR
            return FieldLayout(name, fbs, slot, kind, ref=sub_payload, fixed_len=fixed, bound=bound)
        if sub_node == Nodetype.BASE and sub_payload[0] in STRING_TYPES:
            return FieldLayout(
                name, fbs, slot, FieldKind.STRING_VECTOR, fixed_len=fixed, bound=bound
            )
        if sub_node == Nodetype.BASE:
            scalar = _scalar(owner, name, sub_payload[0])
            return FieldLayout(
                name, fbs, slot, FieldKind.SCALAR_VECTOR, scalar=scalar, fixed_len=fixed,
                bound=bound,
            )
    raise WireError(f"{owner}.{name}: unsupported field definition {desc!r}")


def _scalar(owner: str, field: str, base: str) -> Any:
    try:
        return SCALARS[base]
    except KeyError:
        raise WireError(f"{owner}.{field}: unsupported base type {base!r}") from None


def _shipped_msg_texts() -> dict[str, str]:
    root = resources.files("fleetctl.wire") / "msg"
    texts: dict[str, str] = {}
    for pkg in root.iterdir():
        msg_dir = pkg / "msg"
        if not msg_dir.is_dir():
            continue
        for entry in msg_dir.iterdir():
            if entry.name.endswith(".msg"):
                texts[f"{pkg.name}/msg/{entry.name[:-4]}"] = entry.read_text(encoding="utf-8")
    return texts


def default_prefixes() -> tuple[str, ...]:
    """The install prefixes :meth:`TypeRegistry.from_rclpy` reads by default, in order:
    each of ``AMENT_PREFIX_PATH``, then ``sys.prefix`` (where the ROS wheels put theirs)."""
    ament = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return tuple(dict.fromkeys([*ament, sys.prefix]))


def _installed_msg_files(prefixes: Iterable[str] | None) -> list[Path]:
    if prefixes is None:
        prefixes = default_prefixes()
    files: list[Path] = []
    for prefix in dict.fromkeys(prefixes):
        files.extend(sorted(Path(prefix, "share").glob("*/msg/*.msg")))
    return files
