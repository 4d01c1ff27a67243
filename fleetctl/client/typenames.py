"""Which message types a client config may name: the wire registry's, and those the robot's
installed ROS packages define.

The client's run-time registry (:func:`fleetctl.client.ros.runner.build_registry`) is the
default one (rosbags' Jazzy store and fleetctl's shipped types) plus every ``.msg`` of the
installed packages (``<prefix>/share/<pkg>/msg/*.msg`` for each prefix of
``AMENT_PREFIX_PATH`` and ``sys.prefix``: :meth:`TypeRegistry.from_rclpy`). The config
check asked the default registry alone, so a robot's own message package
(``my_robot_msgs/msg/Status``, built in its workspace) was refused at load as "not in the
type registry", although the client would have carried it. The check now asks the same
two sources, in that order: the installed packages are read only for a name the default
registry lacks (parsing them costs ~0.5 s), once per set of prefixes.
"""

from __future__ import annotations

import difflib
import os
from functools import lru_cache
from typing import Any


def installed_prefixes() -> tuple[str, ...]:
    """The prefixes :meth:`TypeRegistry.from_rclpy` reads by default, in its order."""
    from fleetctl.wire.registry import default_prefixes

    return default_prefixes()


@lru_cache(maxsize=1)
def default_names() -> frozenset[str] | None:
    """The default registry's type names, or None when the wire package is unavailable."""
    try:
        from fleetctl.wire.registry import TypeRegistry
    except ImportError:
        return None
    return frozenset(TypeRegistry.default().names())


@lru_cache(maxsize=4)
def installed_names(prefixes: tuple[str, ...]) -> tuple[frozenset[str], str]:
    """The type names of the default registry plus those the packages under *prefixes*
    define, and why some could not be read ('' when all could). As in the client's
    registry, a definition that does not parse or names an undefined type leaves out
    what it breaks, and the rest stays usable."""
    from fleetctl.wire.registry import TypeRegistry

    registry = TypeRegistry.default()
    try:
        registry.from_rclpy(prefixes)
    except Exception as exc:  # a package's odd .msg: the client runs without it too
        return frozenset(n for n in registry.names() if _usable(registry, n)), str(exc)
    return frozenset(registry.names()), ""


def _usable(registry: Any, name: str) -> bool:
    try:
        registry.get(name)
    except Exception:  # WireError: a field of a type nobody defines
        return False
    return True


def check_type(name: str) -> tuple[str, str]:
    """``(normalized name, "")``, or ``(name, reason)`` for a malformed or unknown type."""
    try:
        from fleetctl.wire.metadata import normalize_type
    except ImportError:
        return name, ""
    try:
        normalized = normalize_type(name)
    except Exception as exc:  # the wire module's WireError; message says why
        return name, f"not a ROS type name: {exc}"
    known = default_names()
    if known is None or normalized in known:
        return normalized, ""
    prefixes = installed_prefixes()
    names, failure = installed_names(prefixes)
    if normalized in names:
        return normalized, ""
    return name, _unknown(name, normalized, names, prefixes, failure)


def _unknown(name: str, normalized: str, names: frozenset[str], prefixes: tuple[str, ...],
             failure: str) -> str:
    package, _, short = normalized.partition("/msg/")
    close = difflib.get_close_matches(normalized, sorted(names), n=1, cutoff=0.8)
    hint = f" Did you mean {close[0]}?" if close else ""
    where = f"share/{package}/msg/{short}.msg under {os.pathsep.join(prefixes)}"
    reason = (f"unknown message type {name!r}: not a ROS 2 Jazzy or fleetctl type, and no "
              f"installed package defines it ({where}).{hint}")
    if failure:
        return f"{reason} The installed packages' definitions could not be read: {failure}"
    return (f"{reason} A package of your own: source its workspace's install/setup.bash "
            "before the client starts (the robot bundle's wrapper: FLEETCTL_ROS_SETUP)")
