"""Read a YAML file, turning every failure into a :class:`ConfigError` naming the file.

Used by every component that loads a YAML config (server config, auth map, robot client
config, compose state); ``fleet.yaml`` has its own line-tracking reader
(:mod:`fleetctl.deploy.yamlnodes`) because its errors name the line of each field.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from fleetctl.errors import ConfigError
from fleetctl.smallfile import read_small_text


def read_yaml(path: Path, what: str) -> Any:
    """Parse the YAML document in *path*; *what* names the file's role in errors.

    Returns:
        The document (``None`` for an empty file).

    Raises:
        ConfigError: ``PATH: cannot read WHAT: REASON`` or ``PATH: not valid YAML: ...``.
    """
    try:
        text = read_small_text(path)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: cannot read {what}: not UTF-8 text") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
