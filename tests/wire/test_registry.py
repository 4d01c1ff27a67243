"""Tests of fleetctl.wire.registry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fleetctl.wire.codec import Codec
from fleetctl.wire.errors import WireError
from fleetctl.wire.layout import FieldKind
from fleetctl.wire.registry import TypeRegistry


def _write_msg(prefix: Path, pkg: str, name: str, text: str) -> None:
    path = prefix / "share" / pkg / "msg" / f"{name}.msg"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_default_has_store_and_shipped_types() -> None:
    registry = TypeRegistry.default()
    assert "sensor_msgs/LaserScan" in registry and "RobofleetStatus" in registry
    assert "fleetctl_msgs/msg/Fragment" in registry and "no/Such" not in registry
    assert "not a name" not in registry


def test_layout_kinds_and_slots() -> None:
    layout = TypeRegistry.default().get("sensor_msgs/msg/CameraInfo")
    by_name = {f.name: f for f in layout.fields}
    assert layout.first_slot == 1 and by_name["header"].slot == 1
    assert by_name["header"].kind is FieldKind.TABLE
    assert by_name["k"].kind is FieldKind.SCALAR_VECTOR and by_name["k"].fixed_len == 9
    assert TypeRegistry.default().get("std_msgs/msg/Header").fields[0].kind is FieldKind.STRUCT


def test_from_installed_prefix_registers_new_types(tmp_path: Path) -> None:
    _write_msg(tmp_path, "warehouse_msgs", "Shelf",
               "std_msgs/Header header\nstring[<=4] labels\nwarehouse_msgs/Bin[] bins\n"
               "int32 MAX=3\n")
    _write_msg(tmp_path, "warehouse_msgs", "Bin", "uint16 id\nfloat64[3] size_m\n")
    _write_msg(tmp_path, "std_msgs", "Header", "this is not parsed: the store has Header\n")
    registry = TypeRegistry.default()
    added = registry.from_rclpy(prefixes=[str(tmp_path)])
    assert added == ["warehouse_msgs/msg/Bin", "warehouse_msgs/msg/Shelf"]
    codec = Codec(registry)
    shelf_cls = registry.get("warehouse_msgs/Shelf").cls
    bin_cls = registry.get("warehouse_msgs/Bin").cls
    header = registry.get("std_msgs/msg/Header").cls(
        registry.get("builtin_interfaces/msg/Time").cls(1, 2), "shelf")
    msg = shelf_cls(header, ["a", "b"], [bin_cls(7, np.array([1.0, 2.0, 3.0]))])
    _meta, back = codec.decode(codec.encode(msg, "warehouse_msgs/Shelf", "/w/shelf"))
    assert back.labels == ["a", "b"] and back.bins[0].id == 7
    assert np.array_equal(back.bins[0].size_m, [1.0, 2.0, 3.0])


def test_bad_msg_text_is_a_wire_error() -> None:
    registry = TypeRegistry.default()
    with pytest.raises(WireError, match=r"cannot parse the \.msg text of x_msgs/msg/Bad"):
        registry.add_msg_text("x_msgs/Bad", "int32 = = oops\n")
    with pytest.raises(WireError, match="cannot register"):
        registry.add_msg_text("std_msgs/msg/String", "int32 data\n")


def test_installed_definition_with_missing_dependency_is_a_wire_error(tmp_path: Path) -> None:
    _write_msg(tmp_path, "a_msgs", "A", "b_msgs/B b\n")
    registry = TypeRegistry.default()
    with pytest.raises(WireError, match=r"a_msgs/msg/A\.b: unknown message type b_msgs/msg/B"):
        registry.from_rclpy(prefixes=[str(tmp_path)])
    with pytest.raises(WireError, match=r"a_msgs/msg/A\.b: unknown message type b_msgs/msg/B"):
        Codec(registry).encode(object(), "a_msgs/A", "/a")


@pytest.mark.ros
def test_installed_ros_wheels_add_types_missing_from_the_store(tmp_path: Path) -> None:
    # nav_msgs/msg/Goals was the example here until fleetctl shipped it (fleetctl/wire/msg).
    registry = TypeRegistry.default()
    assert "nav_msgs/msg/Goals" not in registry.from_rclpy()
    package = tmp_path / "share" / "my_robot_msgs" / "msg"
    package.mkdir(parents=True)
    (package / "Status.msg").write_text("std_msgs/Header header\nfloat32 charge\n")
    assert registry.from_rclpy([str(tmp_path)]) == ["my_robot_msgs/msg/Status"]
    registry.get("my_robot_msgs/msg/Status")
