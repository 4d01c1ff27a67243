"""Realistic sample messages (for benchmarks, tests and simulated robots).

Sizes follow common sensors: a 720-beam 2D lidar, a 32-beam 3D lidar (~1 MB PointCloud2),
a 640x480 JPEG of about 75 KB, and a 384 x 384 SLAM map at 5 cm (the size the ROS 2
navigation tutorials' maps have).
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


_FREE, _OCCUPIED, _UNKNOWN = 0, 100, -1


def occupancy_grid(
    registry: TypeRegistry, size: int = 384, *, resolution_m: float = 0.05, seed: int = 0
) -> Any:
    """A ``nav_msgs/msg/OccupancyGrid`` like a 2D SLAM map of an office floor.

    Unknown (-1) outside the explored building, free (0) inside, occupied (100) walls two
    cells thick with a door gap in each inner wall, furniture blocks with an unknown shadow
    beside them, and lidar speckle (isolated occupied cells) along the walls.
    """
    rng = np.random.default_rng(seed)
    cells = np.full((size, size), _UNKNOWN, dtype=np.int8)
    lo, hi = size // 8, size - size // 8
    cells[lo:hi, lo:hi] = _FREE
    for edge in (lo, hi - 2):
        cells[edge:edge + 2, lo:hi] = _OCCUPIED
        cells[lo:hi, edge:edge + 2] = _OCCUPIED
    for x in np.linspace(lo, hi, 5, dtype=int)[1:-1]:  # inner walls, each with a door
        door = int(rng.integers(lo + 10, hi - 30))
        cells[lo:hi, x:x + 2] = _OCCUPIED
        cells[door:door + 18, x:x + 2] = _FREE
    for _ in range(24):  # furniture and the unknown shadow the lidar could not see
        r, c = (int(v) for v in rng.integers(lo + 6, hi - 16, 2))
        h, w = (int(v) for v in rng.integers(3, 10, 2))
        cells[r:r + h + 4, c:c + w] = np.where(cells[r:r + h + 4, c:c + w] == _FREE, _UNKNOWN,
                                               cells[r:r + h + 4, c:c + w])
        cells[r:r + h, c:c + w] = _OCCUPIED
    free = np.flatnonzero(cells == _FREE)
    speckle = rng.choice(free, size=free.size // 200, replace=False)
    cells.reshape(-1)[speckle] = _OCCUPIED
    pose_cls = registry.get("geometry_msgs/msg/Pose").cls
    point = registry.get("geometry_msgs/msg/Point").cls(-size * resolution_m / 2,
                                                        -size * resolution_m / 2, 0.0)
    origin = pose_cls(point, registry.get("geometry_msgs/msg/Quaternion").cls(0.0, 0.0, 0.0, 1.0))
    stamp = header(registry, "map").stamp
    info = registry.get("nav_msgs/msg/MapMetaData").cls(stamp, resolution_m, size, size, origin)
    return registry.get("nav_msgs/msg/OccupancyGrid").cls(
        header(registry, "map"), info, cells.reshape(-1))
