"""Sample messages of the types the page draws or sends, for decoder and browser tests."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fleetctl.wire.registry import TypeRegistry
from tests.webviz.msgs import make

Sample = tuple[str, str, Any]
"""(type name, topic, rosbags message)."""


def header(frame_id: str = "map", sec: int = 1_700_000_000, nanosec: int = 5) -> dict[str, Any]:
    return {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": frame_id}


def scan_values(beams: int = 360, radius_m: float = 3.0) -> dict[str, Any]:
    angles = np.linspace(-math.pi, math.pi, beams, endpoint=False, dtype=np.float32)
    ranges = (radius_m + 0.5 * np.sin(4 * angles)).astype(np.float32)
    return {
        "header": header("laser"),
        "angle_min": -math.pi,
        "angle_max": math.pi,
        "angle_increment": 2 * math.pi / beams,
        "range_min": 0.1,
        "range_max": 10.0,
        "ranges": ranges,
        "intensities": np.arange(beams, dtype=np.float32),
    }


def cloud_values(points: int = 2000) -> dict[str, Any]:
    t = np.linspace(0, 8 * math.pi, points, dtype=np.float32)
    xyz = np.stack([3 * np.cos(t), 3 * np.sin(t), t / 10], axis=1).astype(np.float32)
    field = [{"name": n, "offset": 4 * i, "datatype": 7, "count": 1} for i, n in enumerate("xyz")]
    return {
        "header": header("lidar"),
        "height": 1,
        "width": points,
        "fields": field,
        "is_bigendian": False,
        "point_step": 12,
        "row_step": 12 * points,
        "data": np.frombuffer(xyz.tobytes(), dtype=np.uint8),
        "is_dense": True,
    }


def pose_values(x: float, y: float, yaw: float) -> dict[str, Any]:
    return {
        "position": {"x": x, "y": y, "z": 0.0},
        "orientation": {"z": math.sin(yaw / 2), "w": math.cos(yaw / 2)},
    }


def samples(
    registry: TypeRegistry, robot: str = "r1", jpeg: bytes = b"\xff\xd8\xff\xd9"
) -> list[Sample]:
    """One message of every type the page handles."""
    p = f"/{robot}"
    cov = np.arange(36, dtype=np.float64) / 7
    marker = {
        "header": header(),
        "ns": "demo",
        "id": 3,
        "type": 4,
        "action": 0,
        "pose": pose_values(1.0, 2.0, 0.3),
        "scale": {"x": 0.1, "y": 0.1, "z": 0.4},
        "color": {"r": 1.0, "g": 0.5, "b": 0.0, "a": 1.0},
        "lifetime": {"sec": 2, "nanosec": 7},
        "points": [{"x": 0.0, "y": 0.0}, {"x": 1.0, "y": 1.5, "z": -2.0}],
        "colors": [{"r": 0.1, "g": 0.2, "b": 0.3, "a": 1.0}],
        "text": "héllo ✓",
    }
    return [
        (
            "sensor_msgs/msg/LaserScan",
            f"{p}/scan",
            make(registry, "sensor_msgs/msg/LaserScan", scan_values()),
        ),
        (
            "sensor_msgs/msg/PointCloud2",
            f"{p}/points",
            make(registry, "sensor_msgs/msg/PointCloud2", cloud_values()),
        ),
        (
            "sensor_msgs/msg/CompressedImage",
            f"{p}/camera/image/compressed",
            make(
                registry,
                "sensor_msgs/msg/CompressedImage",
                {
                    "header": header("cam"),
                    "format": "jpeg",
                    "data": np.frombuffer(jpeg, dtype=np.uint8),
                },
            ),
        ),
        (
            "nav_msgs/msg/Odometry",
            f"{p}/odom",
            make(
                registry,
                "nav_msgs/msg/Odometry",
                {
                    "header": header("odom"),
                    "child_frame_id": "base_link",
                    "pose": {"pose": pose_values(1.5, -2.0, 1.0), "covariance": cov},
                    "twist": {
                        "twist": {"linear": {"x": 0.5}, "angular": {"z": 0.25}},
                        "covariance": cov,
                    },
                },
            ),
        ),
        (
            "geometry_msgs/msg/PoseWithCovarianceStamped",
            f"{p}/pose",
            make(
                registry,
                "geometry_msgs/msg/PoseWithCovarianceStamped",
                {
                    "header": header(),
                    "pose": {"pose": pose_values(1.5, -2.0, 1.0), "covariance": cov},
                },
            ),
        ),
        (
            "geometry_msgs/msg/PoseStamped",
            f"{p}/goal_pose",
            make(
                registry,
                "geometry_msgs/msg/PoseStamped",
                {"header": header(), "pose": pose_values(-1.0, 4.0, -2.0)},
            ),
        ),
        (
            "visualization_msgs/msg/MarkerArray",
            f"{p}/markers",
            make(
                registry,
                "visualization_msgs/msg/MarkerArray",
                {"markers": [marker, {**marker, "id": 4, "type": 9}]},
            ),
        ),
        (
            "sensor_msgs/msg/NavSatFix",
            f"{p}/gps/fix",
            make(
                registry,
                "sensor_msgs/msg/NavSatFix",
                {
                    "header": header("gps"),
                    "status": {"status": 0, "service": 1},
                    "latitude": 30.2862,
                    "longitude": -97.7365,
                    "altitude": 150.5,
                    "position_covariance": np.ones(9),
                    "position_covariance_type": 2,
                },
            ),
        ),
        (
            "nav_msgs/msg/OccupancyGrid",
            f"{p}/map",
            make(
                registry,
                "nav_msgs/msg/OccupancyGrid",
                {
                    "header": header(),
                    "info": {
                        "resolution": 0.5,
                        "width": 4,
                        "height": 3,
                        "origin": pose_values(-1.0, -1.0, 0.0),
                    },
                    "data": np.array([-1, 0, 100, 50] * 3, dtype=np.int8),
                },
            ),
        ),
        (
            "amrl_msgs/msg/RobofleetStatus",
            f"{p}/status",
            make(
                registry,
                "amrl_msgs/msg/RobofleetStatus",
                {"status": "driving", "is_ok": True, "battery_level": 0.75, "location": "lab"},
            ),
        ),
        (
            "amrl_msgs/msg/RobofleetSubscription",
            "/subscriptions",
            make(
                registry,
                "amrl_msgs/msg/RobofleetSubscription",
                {"topic_regex": f"{p}/.*", "action": 1},
            ),
        ),
        (
            "sensor_msgs/msg/JointState",
            f"{p}/joints",
            make(
                registry,
                "sensor_msgs/msg/JointState",
                {"header": header(), "name": ["a", "bb", ""], "position": [1.0, -2.0, 3.5]},
            ),
        ),
        (
            "std_msgs/msg/UInt64",
            f"{p}/big",
            make(registry, "std_msgs/msg/UInt64", {"data": 2**64 - 2}),
        ),
        (
            "std_msgs/msg/Int64MultiArray",
            f"{p}/ints",
            make(
                registry,
                "std_msgs/msg/Int64MultiArray",
                {"data": np.array([-(2**63), 2**63 - 1, 0], dtype=np.int64)},
            ),
        ),
    ]
