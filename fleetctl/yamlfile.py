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
        ConfigError: ``PATH: cannot read WHAT: REASON`` or ``PATH:LINE: not valid YAML: ...``
            (one line).
    """
    try:
        text = read_small_text(path)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: cannot read {what}: not UTF-8 text") from None
    try:
        return safe_load(text)
    except yaml.YAMLError as exc:
        raise yaml_error(path, exc) from None
    except RecursionError:
        raise ConfigError(f"{path}: not valid YAML: {TOO_DEEP}") from None


class _CheckedLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` whose explicitly tagged scalars fail as YAML errors.

    PyYAML's safe constructors turn ``!!int x`` into ``ValueError``, ``!!bool x`` into
    ``KeyError`` and ``!!timestamp x`` into ``AttributeError``: exceptions no caller of a
    YAML loader expects. Each is re-raised as a ``ConstructorError`` marked with the node's
    line.
    """

    def construct_object(self, node: yaml.Node, deep: bool = False) -> Any:
        try:
            return super().construct_object(node, deep)
        except (ValueError, KeyError, TypeError, AttributeError, OverflowError):
            tag = str(node.tag).replace("tag:yaml.org,2002:", "!!")
            value = node.value if isinstance(node, yaml.ScalarNode) else "..."
            raise yaml.constructor.ConstructorError(
                None, None, f"{str(value)[:40]!r} is not a valid {tag} value",
                node.start_mark) from None


def safe_load(text: str) -> Any:
    """``yaml.safe_load`` whose every failure on bad input is a ``yaml.YAMLError`` (or a
    ``RecursionError`` for deep nesting), never another exception."""
    return yaml.load(text, Loader=_CheckedLoader)


# PyYAML's parser recurses once per level of nesting: a few hundred "[" exhaust Python's
# stack. No config of ours nests more than a handful of levels.
TOO_DEEP = "nested too deeply"


def yaml_error(path: Path, exc: yaml.YAMLError) -> ConfigError:
    """``PATH:LINE: not valid YAML: PROBLEM`` on one line (PyYAML's own message spans
    several lines and names ``<unicode string>`` instead of the file)."""
    if isinstance(exc, yaml.MarkedYAMLError):
        mark = exc.problem_mark or exc.context_mark
        line = f":{mark.line + 1}" if mark is not None else ""
        problem = exc.problem or exc.context or "not valid YAML"
        return ConfigError(f"{path}{line}: not valid YAML: {problem}")
    return ConfigError(f"{path}: not valid YAML: {exc}")
