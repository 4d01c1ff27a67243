"""Unit tests of message class resolution."""

from __future__ import annotations

from typing import Any

import pytest

from fleetctl.client.ros.msgtypes import message_class, ros2_type_name, split_type_name
from fleetctl.errors import ConfigError


@pytest.mark.parametrize(
    ("name", "expected"),
    [("sensor_msgs/msg/LaserScan", ("sensor_msgs", "LaserScan")),
     ("std_msgs/String", ("std_msgs", "String")),
     (" geometry_msgs/msg/PoseStamped ", ("geometry_msgs", "PoseStamped"))],
)
def test_split_accepts_ros1_and_ros2_forms(name: str, expected: tuple[str, str]) -> None:
    assert split_type_name(name) == expected


@pytest.mark.parametrize("name", ["LaserScan", "a/b/c/d", "pkg/srv/Name", "pkg/1bad", "../x"])
def test_split_rejects_other_shapes(name: str) -> None:
    with pytest.raises(ConfigError, match="pkg/msg/Name"):
        split_type_name(name)


def test_ros2_type_name() -> None:
    assert ros2_type_name("nav_msgs/Odometry") == "nav_msgs/msg/Odometry"


@pytest.mark.ros
def test_message_class_imports_the_generated_class() -> None:
    pytest.importorskip("rclpy")
    cls = message_class("sensor_msgs/msg/LaserScan")
    assert cls.__name__ == "LaserScan"
    assert cls.__module__.startswith("sensor_msgs.msg")


def test_missing_package_names_the_wheel() -> None:
    with pytest.raises(ConfigError, match="ros-jazzy-no-such-msgs"):
        message_class("no_such_msgs/msg/Thing")


@pytest.mark.parametrize("package", ["tf2_msgs", "foxglove_msgs"])
def test_a_package_pypi_has_no_wheel_for_names_apt_and_ros_msgs(
        package: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The hint was 'install the ROS wheel for tf2_msgs, e.g. ros-jazzy-tf2-msgs', which
    pip cannot find: only apt and scripts/ros_msgs.sh provide these."""
    import sys

    monkeypatch.setitem(sys.modules, f"{package}.msg", None)  # as where it is not installed
    with pytest.raises(ConfigError) as info:
        message_class(f"{package}/msg/Thing")
    message = str(info.value)
    debian = f"ros-jazzy-{package.replace('_', '-')}"
    assert "PyPI has no wheel" in message and f"apt install {debian}" in message
    assert "scripts/ros_msgs.sh" in message and "install the ROS wheel" not in message


@pytest.mark.ros
def test_missing_message_in_an_installed_package() -> None:
    pytest.importorskip("std_msgs")
    with pytest.raises(ConfigError, match="has no message 'Nope'"):
        message_class("std_msgs/msg/Nope")


FAKE_GENERATED = '''\
from rosidl_generator_py import import_type_support


class Metaclass_Status(type):
    _TYPE_SUPPORT = None

    @classmethod
    def __import_type_support__(cls):
        # What rosidl generates: its libraries are not on the loader's path here.
        cls._TYPE_SUPPORT = import_type_support("fake_ws_msgs").type_support


class Status(metaclass=Metaclass_Status):
    pass
'''


@pytest.mark.ros
def test_a_package_whose_type_support_does_not_load_is_a_config_error(
        tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """A workspace's package on PYTHONPATH without its libraries on LD_LIBRARY_PATH: the
    client exited with rclpy's UnsupportedTypeSupport traceback when it subscribed."""
    pytest.importorskip("rclpy")
    package = tmp_path / "fake_ws_msgs"
    (package / "msg").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "msg" / "__init__.py").write_text(FAKE_GENERATED)
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ConfigError) as info:
        message_class("fake_ws_msgs/msg/Status")
    message = str(info.value)
    assert message.startswith("message type 'fake_ws_msgs/msg/Status': Python package "
                              "fake_ws_msgs.msg is installed but its C type support does not "
                              "load (No module named 'fake_ws_msgs.fake_ws_msgs_s__")
    assert message.endswith("source the install/setup.bash of the workspace or ROS that "
                            "built it (it sets LD_LIBRARY_PATH too)")
