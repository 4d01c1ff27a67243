"""Reading YAML through its node tree, so every error can name the file, line and field."""

from __future__ import annotations

import copy
import math
import re
from collections.abc import Iterable
from pathlib import Path

import yaml

from fleetctl.errors import ConfigError
from fleetctl.yamlfile import TOO_DEEP, safe_load, yaml_error

FieldPath = tuple[str | int, ...]

_STR = "tag:yaml.org,2002:str"
_INT = "tag:yaml.org,2002:int"
_FLOAT = "tag:yaml.org,2002:float"
_NULL = "tag:yaml.org,2002:null"
_BOOL = "tag:yaml.org,2002:bool"
# An integer as fleet.yaml may write it: decimal ASCII digits, no leading zero, a sign.
_DECIMAL = re.compile(r"[-+]?(0|[1-9][0-9]{0,29})")


def shown(value: str, limit: int = 40) -> str:
    """Return ``repr(value)``, cut to about *limit* characters (for one-line errors)."""
    return repr(value) if len(value) <= limit else repr(value[:limit]) + "..."


class FleetInvalid(Exception):
    """A semantic error in a fleet, with the field path it concerns.

    Attributes:
        path: the field, e.g. ``("robots", 2, "ip")``.
        conflict: True when the problem is a duplicate (a name or address already used).
    """

    def __init__(self, path: FieldPath, message: str, *, conflict: bool = False) -> None:
        super().__init__(message)
        self.path = path
        self.conflict = conflict


def format_path(path: FieldPath) -> str:
    """Return ``robots[1].ip`` for ``("robots", 1, "ip")``."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
    return out or "(document)"


class _AliasLineLoader(yaml.SafeLoader):
    """A SafeLoader whose aliases carry their own line.

    ``yaml.compose`` gives an alias the very node of its anchor, start mark and all, so
    an error in a value written ``*name`` named the anchor's line. Here each alias is a
    shallow copy of that node (same tag, same value, children shared) marked where the
    alias is written; what is inside it is still reported where it is written, at the
    anchor.
    """

    def compose_node(self, parent: yaml.Node | None, index: int) -> yaml.Node | None:
        if not self.check_event(yaml.AliasEvent):
            return super().compose_node(parent, index)
        event = self.peek_event()  # type: ignore[no-untyped-call]
        node = super().compose_node(parent, index)
        if node is None:
            return None
        twin = copy.copy(node)
        twin.start_mark, twin.end_mark = event.start_mark, event.end_mark
        return twin


class Document:
    """One YAML file's node tree, with error helpers that name file, line and field.

    Every node read through this class has its line remembered under its field path, so
    semantic checks done later on the built objects can still point at the right line.
    """

    def __init__(self, path: Path, text: str) -> None:
        self.path = path
        self.lines: dict[FieldPath, int] = {}
        try:
            root = yaml.compose(text, Loader=_AliasLineLoader)
        except yaml.YAMLError as exc:
            raise yaml_error(path, exc) from None
        except RecursionError:  # PyYAML's composer recurses per level: "[[[[..."
            raise ConfigError(f"{path}: not valid YAML: {TOO_DEEP}") from None
        if root is None:
            raise ConfigError(f"{path}:1: the file is empty")
        self.root = root

    def line_of(self, path: FieldPath) -> int:
        """Return the line of *path*, or of its nearest ancestor that was read."""
        while path and path not in self.lines:
            path = path[:-1]
        return self.lines.get(path, self.root.start_mark.line + 1)

    def error(self, path: FieldPath, message: str) -> ConfigError:
        """Return a :class:`ConfigError` ``FILE:LINE: FIELD: MESSAGE``."""
        return ConfigError(f"{self.path}:{self.line_of(path)}: {format_path(path)}: {message}")

    def _seen(self, node: yaml.Node, path: FieldPath) -> yaml.Node:
        self.lines[path] = node.start_mark.line + 1
        return node

    def mapping(
        self, node: yaml.Node, path: FieldPath, required: Iterable[str], optional: Iterable[str]
    ) -> dict[str, yaml.Node]:
        """Return a mapping's fields; unknown, duplicate or missing fields are errors."""
        self._seen(node, path)
        if not isinstance(node, yaml.MappingNode):
            raise self.error(path, "expected a mapping")
        allowed = set(required) | set(optional)
        fields: dict[str, yaml.Node] = {}
        for key_node, value in node.value:
            key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
            sub = (*path, str(key))
            if key not in allowed:
                self._seen(key_node, sub)
                expected = ", ".join(sorted(allowed))
                raise self.error(sub, f"unknown field (expected one of {expected})")
            if key in fields:
                self._seen(key_node, sub)
                raise self.error(sub, "duplicate field")
            fields[key] = self._seen(value, sub)
        for key in required:
            if key not in fields:
                raise self.error(path, f"missing required field '{key}'")
        return fields

    def sequence(self, node: yaml.Node, path: FieldPath) -> list[yaml.Node]:
        """Return a sequence's items (``null`` is an empty sequence)."""
        self._seen(node, path)
        if isinstance(node, yaml.ScalarNode) and node.tag == _NULL:
            return []
        if not isinstance(node, yaml.SequenceNode):
            raise self.error(path, "expected a list")
        return [self._seen(item, (*path, i)) for i, item in enumerate(node.value)]

    def string(self, node: yaml.Node, path: FieldPath) -> str:
        """Return a string scalar (numbers are not silently turned into strings)."""
        self._seen(node, path)
        if not isinstance(node, yaml.ScalarNode) or node.tag != _STR:
            raise self.error(path, "expected a string")
        return str(node.value)

    def integer(self, node: yaml.Node, path: FieldPath, low: int, high: int) -> int:
        """Return an integer scalar in ``[low, high]``, written in decimal ASCII digits.

        YAML 1.1 also reads ``0x1f90``, ``0o17``, ``0b1``, ``8_080``, ``017`` (octal) and
        ``2:13:20`` (base 60) as integers; those are refused, as are other scripts' digits
        (``int()`` reads them): what the file says is the number it means.
        """
        self._seen(node, path)
        if not isinstance(node, yaml.ScalarNode) or node.tag != _INT:
            raise self.error(path, "expected an integer")
        text = str(node.value)
        if not _DECIMAL.fullmatch(text):
            raise self.error(path, f"expected an integer in decimal ASCII digits without "
                             f"leading zeros, got {text[:40]!r}")
        value = int(text)
        if not low <= value <= high:
            raise self.error(path, f"must be between {low} and {high}, got {value}")
        return value

    def is_null(self, node: yaml.Node) -> bool:
        """Return True for a ``null`` / ``~`` / empty scalar."""
        return isinstance(node, yaml.ScalarNode) and node.tag == _NULL

    def optional_string(self, node: yaml.Node, path: FieldPath) -> str | None:
        """Return a string scalar, or ``None`` for ``null``."""
        self._seen(node, path)
        return None if self.is_null(node) else self.string(node, path)

    def number(self, node: yaml.Node, path: FieldPath) -> float:
        """Return a finite integer or float scalar as a float."""
        self._seen(node, path)
        if not isinstance(node, yaml.ScalarNode) or node.tag not in (_INT, _FLOAT):
            raise self.error(path, "expected a number")
        text = str(node.value)
        try:
            if not text.isascii():  # float() and int() read other scripts' digits
                raise ValueError(text)
            # A quoted "!!float" value is any text: reading it may fail as YAML too.
            value = float(int(text.replace("_", ""), 0)) if node.tag == _INT else (
                float(safe_load(text)))
        except (ValueError, TypeError, yaml.YAMLError, RecursionError):
            raise self.error(path, "expected a number") from None
        except OverflowError:  # an integer of hundreds of digits: no float holds it
            raise self.error(path, f"must be a finite number, got {text[:40]}...") from None
        if not math.isfinite(value):
            raise self.error(path, f"must be a finite number, got {node.value}")
        return value

    def boolean(self, node: yaml.Node, path: FieldPath) -> bool:
        """Return a ``true`` / ``false`` scalar."""
        self._seen(node, path)
        value = None
        if isinstance(node, yaml.ScalarNode) and node.tag == _BOOL:
            # As PyYAML reads a bool; a quoted "!!bool" value is any text (refused).
            value = yaml.constructor.SafeConstructor.bool_values.get(str(node.value).lower())
        if value is None:
            raise self.error(path, "expected true or false")
        return bool(value)
