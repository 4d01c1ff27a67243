"""Resolve ROS 2 message classes from type names (``pkg/msg/Name`` or ``pkg/Name``).

rclpy needs the generated Python class to create a publisher or subscription; the class
lives in the ``pkg.msg`` module that the package's wheel installs. Nothing is hand-written
per type.
"""

from __future__ import annotations

import importlib
from typing import Any

from fleetctl.errors import ConfigError


def split_type_name(type_name: str) -> tuple[str, str]:
    """Split ``pkg/msg/Name`` or ``pkg/Name`` into ``(pkg, Name)``.

    Raises:
        ConfigError: the name has another shape.
    """
    parts = type_name.strip().split("/")
    if len(parts) == 3 and parts[1] == "msg":
        parts = [parts[0], parts[2]]
    if len(parts) != 2 or not all(part.isidentifier() for part in parts):
        raise ConfigError(f"message type {type_name!r} is not of the form pkg/msg/Name")
    return parts[0], parts[1]


def ros2_type_name(type_name: str) -> str:
    """The ROS 2 form ``pkg/msg/Name`` of *type_name* (what the wire and rosbags use)."""
    package, name = split_type_name(type_name)
    return f"{package}/msg/{name}"


# ROS 2 Jazzy message packages fleetctl uses that have no ros-jazzy-* wheel on PyPI: telling
# a pip user to install one sent them after a wheel that does not exist.
_NO_PYPI_WHEEL = frozenset({"tf2_msgs", "foxglove_msgs"})


def _install_hint(package: str) -> str:
    """Where *package* comes from: its PyPI wheel, or apt / scripts/ros_msgs.sh."""
    debian = f"ros-jazzy-{package.replace('_', '-')}"
    if package in _NO_PYPI_WHEEL:
        return (f"PyPI has no wheel for it: apt install {debian} where ROS comes from apt, "
                "or build it into the venv with scripts/ros_msgs.sh from fleetctl's source")
    return (f"install the ROS wheel for {package}, e.g. {debian}; a package of your own: "
            "source its workspace's install/setup.bash before the client starts")


def message_class(type_name: str) -> Any:
    """The rclpy message class of *type_name*.

    Raises:
        ConfigError: the package is not installed or has no such message (the message
            says which, and which wheel provides it).
    """
    package, name = split_type_name(type_name)
    try:
        module = importlib.import_module(f"{package}.msg")
    except ImportError as exc:
        raise ConfigError(f"message type {type_name!r}: Python package {package}.msg is not "
                          f"installed ({_install_hint(package)})") from exc
    cls = getattr(module, name, None)
    if cls is None:
        raise ConfigError(f"message type {type_name!r}: {package}.msg has no message {name!r}")
    _check_type_support(type_name, package, cls)
    return cls


def _check_type_support(type_name: str, package: str, cls: Any) -> None:
    """Load the C type support rclpy needs (at start, where a failure is a config error).

    A package whose Python module imports but whose libraries the dynamic loader cannot
    find (a workspace put on PYTHONPATH by hand, without the LD_LIBRARY_PATH its
    setup.bash sets) made the client exit with rclpy's UnsupportedTypeSupport traceback.

    Raises:
        ConfigError: naming the type, the loader's reason and what to source.
    """
    from rclpy.type_support import check_for_type_support

    try:
        check_for_type_support(cls)
    except Exception as exc:  # rosidl's UnsupportedTypeSupport, rclpy's NoTypeSupport...
        cause = exc.__context__ or exc
        raise ConfigError(
            f"message type {type_name!r}: Python package {package}.msg is installed but "
            f"its C type support does not load ({cause}): source the install/setup.bash "
            "of the workspace or ROS that built it (it sets LD_LIBRARY_PATH too)") from exc
