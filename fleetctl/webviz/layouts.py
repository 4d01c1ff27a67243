"""``/types/<T>.json``: the FlatBuffer layout of a ROS type, for the page's decoder.

The body is :func:`fleetctl.wire.schema.describe` as JSON: derived from the same
:class:`~fleetctl.wire.layout.MessageLayout` objects the Python codec encodes and decodes
with, so the page and the codec cannot disagree. ``static/js/fb/layout.js`` reads it.
"""

from __future__ import annotations

import json
from collections import OrderedDict
from threading import Lock

from fleetctl.wire.errors import WireError
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.schema import describe

MsgTypes = tuple[tuple[str, str], ...]
"""``(pkg/msg/Name, .msg text)`` pairs: a fleet's own message types."""


class LayoutError(Exception):
    """No layout can be given for a requested type name (the message says why)."""


class LayoutCache:
    """JSON bodies of ``describe()`` documents, computed once per type (bounded LRU)."""

    def __init__(self, registry: TypeRegistry, max_types: int = 256) -> None:
        """Serve layouts of *registry*'s types, keeping at most *max_types* bodies."""
        self._registry = registry
        self._max_types = max_types
        self._bodies: OrderedDict[str, bytes] = OrderedDict()
        self._lock = Lock()  # the HTTP server answers from several threads

    def __call__(self, type_name: str) -> bytes:
        """The JSON body for *type_name*.

        Raises:
            LayoutError: the name is malformed or the type unknown (message says which).
        """
        with self._lock:
            body = self._bodies.get(type_name)
            if body is None:
                try:
                    doc = describe(self._registry, type_name)
                except WireError as exc:
                    raise LayoutError(str(exc)) from exc
                body = json.dumps(doc, separators=(",", ":")).encode()
                self._bodies[type_name] = body
                if len(self._bodies) > self._max_types:
                    self._bodies.popitem(last=False)
            self._bodies.move_to_end(type_name)
            return body
