"""One check every optional ``server.yaml`` section shares (``web:``, ``recording:``,
``cluster:`` and their sub-mappings)."""

from __future__ import annotations

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
    unknown = sorted(set(value) - set(known))
    if unknown:
        raise ConfigError(f"{path}: unknown field '{field}.{unknown[0]}'")
    return value
