"""Realistic sample messages (for benchmarks, tests and simulated robots).

Sizes follow common sensors: a 720-beam 2D lidar, a 32-beam 3D lidar (~1 MB PointCloud2),
and a 640x480 JPEG of about 75 KB.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fleetctl.wire.registry import TypeRegistry

_FLOAT32 = 7  # sensor_msgs/msg/PointField.FLOAT32


def header(registry: TypeRegistry, frame_id: str, stamp_ns: int = 1_700_000_000_123_456_789) -> Any:
    """A ``std_msgs/msg/Header`` with *frame_id* and a stamp of *stamp_ns* ns since the epoch."""
    time_cls = registry.get("builtin_interfaces/msg/Time").cls
    stamp = time_cls(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
    return registry.get("std_msgs/msg/Header").cls(stamp, frame_id)


def laser_scan(registry: TypeRegistry, beams: int = 720, *, seed: int = 0) -> Any:
    """A ``sensor_msgs/msg/LaserScan`` over 360 degrees with ranges and intensities."""
    rng = np.random.default_rng(seed)
    increment = float(2 * np.pi / beams)
    ranges = rng.uniform(0.1, 30.0, beams).astype(np.float32)
    intensities = rng.uniform(0.0, 4000.0, beams).astype(np.float32)
    return registry.get("sensor_msgs/msg/LaserScan").cls(
        header(registry, "laser"), -np.pi, np.pi - increment, increment, 1.0 / (40 * beams),
        0.025, 0.1, 30.0, ranges, intensities,
    )


def point_cloud(
    registry: TypeRegistry, rings: int = 32, columns: int = 2048, *, seed: int = 0
) -> Any:
    """A ``sensor_msgs/msg/PointCloud2`` of a *rings*-beam lidar, x y z intensity float32.

    The default 32 x 2048 points x 16 bytes is 1 MiB of point data.
    """
    field_cls = registry.get("sensor_msgs/msg/PointField").cls
    fields = [field_cls(name, 4 * i, _FLOAT32, 1) for i, name in enumerate("xyz")]
    fields.append(field_cls("intensity", 12, _FLOAT32, 1))
    points = np.random.default_rng(seed).normal(0.0, 10.0, (rings * columns, 4))
    data = points.astype(np.float32).view(np.uint8).reshape(-1)
    return registry.get("sensor_msgs/msg/PointCloud2").cls(
        header(registry, "lidar"), rings, columns, fields, False, 16, 16 * columns, data, True,
    )


def compressed_image(registry: TypeRegistry, nbytes: int = 75_000, *, seed: int = 0) -> Any:
    """A ``sensor_msgs/msg/CompressedImage`` with *nbytes* of JPEG-like (incompressible) data."""
    data = np.random.default_rng(seed).integers(0, 256, nbytes, dtype=np.uint8)
    data[:2] = (0xFF, 0xD8)  # JPEG start-of-image marker
    data[-2:] = (0xFF, 0xD9)  # end-of-image marker
    return registry.get("sensor_msgs/msg/CompressedImage").cls(
        header(registry, "camera"), "jpeg", data
    )
