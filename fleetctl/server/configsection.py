"""Checks the ``server.yaml`` sections share (``limits:``, ``web:``, ``recording:``,
``cluster:`` and their sub-mappings)."""

from __future__ import annotations

import math
from collections.abc import Collection
from pathlib import Path
from typing import Any

from fleetctl.errors import ConfigError


def section(value: Any, known: Collection[str], field: str, path: Path) -> dict[str, Any] | None:
    """*value* as a mapping of known keys; ``None`` when the section is absent.

    Args:
        field: The section's dotted name (``cluster.credentials``), for messages.
        path: The config file, for messages.

    Raises:
        ConfigError: Not a mapping, or an unknown key (named with its section).
    """
    if value is None:
        return None
    if not isinstance(value, dict):
        raise ConfigError(f"{path}: field '{field}' must be a mapping")
    unknown = sorted(set(value) - set(known), key=str)  # YAML keys may be numbers or null
    if unknown:
        raise ConfigError(f"{path}: unknown field '{field}.{unknown[0]}'")
    return value


def is_positive_number(value: Any) -> bool:
    """True for a finite int or float above 0: not a bool (YAML's ``true`` is no number),
    not NaN (``.nan <= 0`` is false, like every comparison with NaN), not infinite, and not
    an integer too large for a float (hundreds of digits: ``math.isfinite`` overflows)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        number = float(value)
    except OverflowError:
        return False
    return math.isfinite(number) and number > 0
