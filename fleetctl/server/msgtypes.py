"""The fleet's own message types in ``server.yaml`` (``msg_types``), and the codec of them.

The relay routes frames by topic and needs no message definition, but the parts that
decode do: the web page's ``/types/<T>.json`` layouts and the Foxglove listener (schemas,
FlatBuffer -> CDR). ``fleetctl render`` copies the fleet's own definitions
(``FLEET/msg_types``, :mod:`fleetctl.deploy.msgtypes`) into ``server.yaml`` as
``msg_types: [{type: pkg/msg/Name, definition: <.msg text>}]``: the file the server
already reads, in every deployment (``fleetctl up`` copies it into the container), so no
directory has to be mounted. They are checked at start (a definition that does not parse
or names a type nobody defines is a config error, not a 404 later), and
:func:`codec_for` gives the one codec of a process for them.
"""

from __future__ import annotations

import functools
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fleetctl.errors import ConfigError
from fleetctl.server.configsection import section
from fleetctl.wire.errors import WireError

if TYPE_CHECKING:
    from fleetctl.wire.codec import Codec

MsgTypes = tuple[tuple[str, str], ...]
"""``(pkg/msg/Name, .msg text)`` pairs."""

# The same bounds as the fleet directory's (fleetctl.deploy.msgtypes): the server reads
# what render wrote from there.
MAX_MSG_TYPES = 1000
MAX_DEFINITION_BYTES = 64 << 10
_TYPE_NAME = re.compile(r"[a-z][a-z0-9]*(_[a-z0-9]+)*/msg/[A-Z][A-Za-z0-9]*")
_KEYS = ("type", "definition")


def parse_msg_types(value: Any, path: Path) -> MsgTypes:
    """Validate ``server.yaml``'s ``msg_types`` (absent or ``null``: none).

    Raises:
        ConfigError: Not a list of ``{type, definition}`` mappings within the bounds, a
            name that is not ``pkg/msg/Name`` or given twice, or definitions the registry
            refuses (the message names the file and the field).
    """
    if value is None:
        return ()
    if not isinstance(value, list) or len(value) > MAX_MSG_TYPES:
        raise ConfigError(f"{path}: field 'msg_types' must be a list of at most "
                          f"{MAX_MSG_TYPES} {{type, definition}} mappings")
    entries = [_entry(e, f"msg_types[{i}]", path) for i, e in enumerate(value)]
    names = [name for name, _ in entries]
    if len(set(names)) != len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise ConfigError(f"{path}: field 'msg_types': {twice} is defined twice")
    msg_types = tuple(entries)
    try:
        codec_for(msg_types)
    except WireError as exc:
        raise ConfigError(f"{path}: field 'msg_types': {str(exc).splitlines()[0]}") from None
    return msg_types


def _entry(value: Any, where: str, path: Path) -> tuple[str, str]:
    entry = section(value, _KEYS, where, path)
    if entry is None or set(entry) != set(_KEYS):
        raise ConfigError(f"{path}: field '{where}' must be a mapping of type and definition")
    name, text = entry["type"], entry["definition"]
    if not isinstance(name, str) or not _TYPE_NAME.fullmatch(name):
        raise ConfigError(f"{path}: field '{where}.type' must be a pkg/msg/Name type name")
    if not isinstance(text, str) or len(text.encode("utf-8", "replace")) > MAX_DEFINITION_BYTES:
        raise ConfigError(f"{path}: field '{where}.definition' must be the .msg text, at "
                          f"most {MAX_DEFINITION_BYTES} bytes")
    return name, text


@functools.lru_cache(maxsize=4)
def codec_for(msg_types: MsgTypes) -> Codec:
    """The codec of the default registry plus *msg_types* (built once per set); the
    process-wide :func:`default_codec` when there are none.

    Raises:
        WireError: A definition does not parse, names a type nobody defines, or is of a
            type the default registry has already.
    """
    # Imported here: server.yaml's reader (imported by deploy commands too) stays light.
    from fleetctl.wire.codec import Codec, default_codec
    from fleetctl.wire.registry import TypeRegistry

    if not msg_types:
        return default_codec()
    return Codec(TypeRegistry.default_with(msg_types))
