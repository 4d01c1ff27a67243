"""Readers of the client configuration's fields, each naming file, entry and field in its
errors (``client.yaml: publish[2] (/scan): rate_limit_hz: must be > 0 or null, got -1``).

Used by :mod:`fleetctl.client.config` and :mod:`fleetctl.client.mediaconfig`; every
reader takes the :class:`Ctx` of the document, ``where`` (the entry, e.g.
``publish[2] (/scan)``, empty at the top level) and the field's key.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Mapping
from typing import Any

from fleetctl.errors import ConfigError


class Ctx:
    """Builds error messages that name the file and the place in it.

    Args:
        source: Name of the file (or document) the messages start with.
    """

    def __init__(self, source: str) -> None:
        self.source = source

    def error(self, where: str, field_name: str, reason: str) -> ConfigError:
        """``SOURCE: WHERE: FIELD: REASON`` (WHERE may be empty)."""
        prefix = f"{self.source}: {where}: " if where else f"{self.source}: "
        return ConfigError(f"{prefix}{field_name}: {reason}")


def mapping(
    ctx: Ctx, value: object, where: str, name: str, allowed: frozenset[str]
) -> Mapping[str, Any]:
    """*value* as a mapping whose keys are all in *allowed* (*name* names it if it is not
    a mapping at all)."""
    if not isinstance(value, Mapping):
        raise ctx.error(where, name, f"must be a mapping, got {type(value).__name__}")
    unknown = sorted(str(k) for k in value if k not in allowed)
    if unknown:
        # A typo (``publsh``, ``typ``) gets the field it most likely meant.
        close = difflib.get_close_matches(unknown[0], sorted(allowed), n=1, cutoff=0.75)
        hint = f"did you mean {close[0]}? " if close else ""
        raise ctx.error(where, unknown[0],
                        f"unknown field ({hint}allowed: {', '.join(sorted(allowed))})")
    return value


def sub_mapping(
    ctx: Ctx, value: object, where: str, name: str, allowed: frozenset[str]
) -> Mapping[str, Any]:
    """A mapping nested in an entry: its unknown fields are named ``<where>: <name>: key``."""
    if not isinstance(value, Mapping):
        raise ctx.error(where, name, f"must be a mapping, got {type(value).__name__}")
    return mapping(ctx, value, f"{where}: {name}", name, allowed)


def string(
    ctx: Ctx, entry: Mapping[str, Any], where: str, key: str, *, required: bool = False
) -> str | None:
    """A non-empty string, or None when absent or null (an error if *required*)."""
    value = entry.get(key)
    if value is None:
        if required:
            raise ctx.error(where, key, "is required")
        return None
    if not isinstance(value, str) or not value:
        raise ctx.error(where, key, f"must be a non-empty string, got {value!r}")
    return value


def number(
    ctx: Ctx, entry: Mapping[str, Any], where: str, key: str, default: float | None,
    check: Callable[[float], bool], rule: str,
) -> float | None:
    """A finite number (int or float, not bool) passing *check* (*rule* says it in the
    error), *default* when absent; None when null."""
    value = entry.get(key, default)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ctx.error(where, key, f"must be a number, got {value!r}")
    try:
        number = float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise ctx.error(where, key, f"must be a finite number, got {str(value)[:40]}...") from None
    if not math.isfinite(number) or not check(number):
        raise ctx.error(where, key, f"must be {rule}, got {value!r}")
    return number


def integer(ctx: Ctx, entry: Mapping[str, Any], where: str, key: str, default: int,
         lo: int, hi: int) -> int:
    """An integer (not bool) in ``[lo, hi]``, *default* when absent."""
    value: object = entry.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ctx.error(where, key, f"must be an integer, got {value!r}")
    if not lo <= value <= hi:
        raise ctx.error(where, key, f"must be between {lo} and {hi}, got {value}")
    return value


def boolean(ctx: Ctx, entry: Mapping[str, Any], where: str, key: str, default: bool) -> bool:
    """``true`` or ``false``, *default* when absent."""
    value = entry.get(key, default)
    if not isinstance(value, bool):
        raise ctx.error(where, key, f"must be true or false, got {value!r}")
    return value
