"""The fleet's own message types: ``.msg`` definitions in ``FLEET/msg_types/<pkg>/msg/``.

A robot's own package (``my_robot_msgs/msg/Status``) is carried by its client once its
workspace is sourced (docs/client.md, "Message types"), but fleet.yaml's check knew only the
default registry (rosbags' Jazzy store and fleetctl's shipped types). The fleet directory
now holds the definitions of the fleet's own packages in the layout of a ROS install's
``share/<pkg>/msg`` (so an operator copies a built package's ``msg/`` folder in as it is),
and fleet.yaml's check accepts their types too (docs/operator.md, "The fleet's own message
types").

The definitions are checked as the robot client's registry would use them (the same
:class:`~fleetctl.wire.registry.TypeRegistry`, so the same rosbags parser and the same
layout rules), plus the names rosidl would require of the package, the message and its
fields; every problem is a :class:`ConfigError` naming the file (and its line where there
is one). Reading is bounded: at most :data:`MAX_MSG_FILES` files of at most
:data:`MAX_MSG_BYTES` each, regular files only (:mod:`fleetctl.smallfile`).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from fleetctl.errors import ConfigError
from fleetctl.smallfile import read_small_text

if TYPE_CHECKING:
    from fleetctl.wire.registry import TypeRegistry

MSG_TYPES_DIR = "msg_types"
# The largest .msg of ROS 2 Jazzy is ~12 KB, mostly comments; 64 KiB is no real message.
MAX_MSG_BYTES = 64 << 10
# A robot software stack has tens of own messages; a thousand is a copied tree gone wrong.
MAX_MSG_FILES = 1000

# REP 144: lowercase letters, digits and single underscores, starting with a letter, at
# least two characters.
_PACKAGE = re.compile(r"[a-z][a-z0-9]*(_[a-z0-9]+)*")
# rosidl: an interface name is CamelCase ASCII letters and digits, starting with a capital.
_MESSAGE = re.compile(r"[A-Z][A-Za-z0-9]*")
# rosidl: a field name as a package name (a single letter too). rosbags' parser already
# refuses a constant that is not in capitals, but takes any field name.
_FIELD = re.compile(r"[a-z][a-z0-9]*(_[a-z0-9]+)*")
# rosbags' parse error ends "...'\n<offset>\n<rest>": the offset into "MSG: <name>\n<text>".
_PARSE_OFFSET = re.compile(r"\n(\d+)\n")

HOW_TO_ADD = (f"copy its msg/ folder (in its workspace: install/PKG/share/PKG/msg) to "
              f"FLEET/{MSG_TYPES_DIR}/PKG/msg/")


@dataclass(frozen=True)
class FleetMsgTypes:
    """The definitions of the fleet's own message packages.

    Attributes:
        directory: where they were read from (``FLEET/msg_types``); ``None``: not read
            (fleet.yaml's text checked alone), so only the default registry's types count.
        texts: ``(pkg/msg/Name, .msg text)`` pairs, sorted by name.
    """

    directory: Path | None = None
    texts: tuple[tuple[str, str], ...] = ()

    @property
    def names(self) -> frozenset[str]:
        """The type names these definitions add (``pkg/msg/Name``)."""
        return frozenset(name for name, _ in self.texts)

    def where(self, name: str) -> str:
        """Where the definition of type *name* (``pkg/msg/Name``) is or would be."""
        package, _, short = name.partition("/msg/")
        root = str(self.directory) if self.directory is not None else f"FLEET/{MSG_TYPES_DIR}"
        return f"{root}/{package}/msg/{short}.msg"


NO_MSG_TYPES = FleetMsgTypes()  # fleet.yaml's text checked alone: the default registry's types


def load_msg_types(fleet_dir: Path) -> FleetMsgTypes:
    """Read and check ``fleet_dir/msg_types`` (absent: no types of the fleet's own).

    Raises:
        ConfigError: a file or directory name that is not a ROS name, a file that cannot
            be read, a definition that does not parse or names a type nobody defines, or
            a type the default registry already has; the message names the file.
    """
    root = fleet_dir / MSG_TYPES_DIR
    if not os.path.lexists(root):
        return FleetMsgTypes(root)
    files = _msg_files(root)
    texts = {name: _read(path) for name, path in files.items()}
    if texts:
        _check_definitions(texts, files)
    return FleetMsgTypes(root, tuple(sorted(texts.items())))


def _entries(directory: Path) -> list[os.DirEntry[str]]:
    """The entries of *directory* by name, hidden ones (``.git``, editors' files) left out."""
    try:
        with os.scandir(directory) as it:
            return sorted((e for e in it if not e.name.startswith(".")), key=lambda e: e.name)
    except OSError as exc:
        raise ConfigError(f"{directory}: cannot read: {exc.strerror or exc}") from None


def _msg_files(root: Path) -> dict[str, Path]:
    """``pkg/msg/Name`` -> file for every ``<pkg>/msg/<Name>.msg`` under *root*.

    Other files are left alone: a README beside the packages, the ``.idl`` files rosidl
    installs beside each ``.msg``, a package's ``srv/`` and ``action/`` (the fleet carries
    messages only).
    """
    if not root.is_dir():
        raise ConfigError(f"{root}: not a directory (it holds the fleet's own message "
                          "packages: PKG/msg/NAME.msg)")
    found: dict[str, Path] = {}
    for package in _entries(root):
        if not package.is_dir():
            continue
        if len(package.name) < 2 or not _PACKAGE.fullmatch(package.name):
            raise ConfigError(f"{package.path}: {package.name!r} is not a ROS package name "
                              "(REP 144: lowercase letters, digits and single underscores, "
                              "starting with a letter)")
        msg_dir = Path(package.path, "msg")
        if not msg_dir.is_dir():
            continue
        for entry in _entries(msg_dir):
            if not entry.name.endswith(".msg"):
                continue
            _check_message_name(entry)
            found[f"{package.name}/msg/{entry.name[:-4]}"] = Path(entry.path)
            if len(found) > MAX_MSG_FILES:
                raise ConfigError(f"{root}: more than {MAX_MSG_FILES} .msg files (copy the "
                                  "msg/ folders of the fleet's own packages only)")
    return found


def _check_message_name(entry: os.DirEntry[str]) -> None:
    if not _MESSAGE.fullmatch(entry.name[:-4]):
        raise ConfigError(f"{entry.path}: {entry.name[:-4]!r} is not a ROS message name "
                          "(CamelCase letters and digits, starting with a capital letter)")


def _read(path: Path) -> str:
    try:
        return read_small_text(path, MAX_MSG_BYTES)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: cannot read: not UTF-8 text") from None


def _check_definitions(texts: dict[str, str], files: dict[str, Path]) -> None:
    """Register every definition in a default registry, as the robot client's would be."""
    from fleetctl.wire.errors import WireError
    from fleetctl.wire.registry import TypeRegistry

    registry = TypeRegistry.default()
    for name, text in texts.items():
        if name in registry:
            raise ConfigError(f"{files[name]}: {name} is a ROS 2 Jazzy or fleetctl type "
                              "already; remove the file (the fleet's definitions add "
                              "packages, they do not replace standard ones)")
        _register(registry, name, text, files[name])
    for name, text in texts.items():
        try:
            registry.get(name)  # every field's type must be defined somewhere
        except WireError as exc:
            raise _field_error(files[name], name, text, str(exc)) from None


def _register(registry: TypeRegistry, name: str, text: str, path: Path) -> None:
    from fleetctl.wire.errors import WireError

    before = set(registry.typestore.fielddefs)
    try:
        registry.add_msg_text(name, text)
    except WireError as exc:
        raise _parse_error(path, name, text, exc) from None
    added = set(registry.typestore.fielddefs) - before
    if added != {name}:  # a ROS 1 style "MSG: other/Type" section defines more
        raise ConfigError(f"{path}: defines {', '.join(sorted(added - {name}))} too: one "
                          "message per file")
    for field_name, *_ in registry.typestore.fielddefs[name][1]:
        if not _FIELD.fullmatch(field_name):
            raise ConfigError(f"{_at(path, text, field_name)}field {field_name!r}: not a ROS "
                              "field name (lowercase letters, digits and single underscores)")


def _parse_error(path: Path, name: str, text: str, exc: Exception) -> ConfigError:
    found = _PARSE_OFFSET.search(str(exc.__cause__ or exc))
    offset = int(found.group(1)) - len(f"MSG: {name}\n") if found else -1
    if not 0 <= offset <= len(text):
        return ConfigError(f"{path}: does not parse as a .msg definition")
    line_no = text.count("\n", 0, offset) + 1
    lines = text.splitlines()
    line = lines[line_no - 1] if line_no <= len(lines) else ""
    return ConfigError(f"{path}:{line_no}: cannot parse {line.strip()[:60]!r} (a line is "
                       "'TYPE name', 'TYPE name DEFAULT' or 'TYPE NAME=VALUE')")


def _field_error(path: Path, name: str, text: str, message: str) -> ConfigError:
    # The registry's message starts "pkg/msg/Name.field: " for a field of this type.
    head, sep, rest = message.partition(": ")
    if sep and head.startswith(f"{name}."):
        field_name = head[len(name) + 1:]
        return ConfigError(f"{_at(path, text, field_name)}field {field_name!r}: {rest}")
    return ConfigError(f"{path}: {message}")


def _at(path: Path, text: str, field_name: str) -> str:
    """``FILE:LINE: `` of the line declaring *field_name* (``FILE: `` if none does)."""
    declared = re.compile(rf"\s*[^\s#]+\s+{re.escape(field_name)}(\s|=|$)")
    for line_no, line in enumerate(text.splitlines(), 1):
        if declared.match(line):
            return f"{path}:{line_no}: "
    return f"{path}: "
