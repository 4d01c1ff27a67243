"""Unit tests of message class resolution."""

from __future__ import annotations

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


@pytest.mark.ros
def test_missing_message_in_an_installed_package() -> None:
    pytest.importorskip("std_msgs")
    with pytest.raises(ConfigError, match="has no message 'Nope'"):
        message_class("std_msgs/msg/Nope")
