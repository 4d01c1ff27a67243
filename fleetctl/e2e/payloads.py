"""Test messages that carry their own publish time and sequence number.

The load publisher stamps every message when it publishes it on ROS; consumers read the
stamp back, so latency is measured from the ROS publish to the consumer's receipt (one host
clock: containers share the kernel's CLOCK_REALTIME).

- Stamped types (``header``): ``header.stamp`` is the publish time, ``header.frame_id`` the
  publisher's per-topic sequence number (decimal).
- ``sensor_msgs/msg/Image`` (rgb8, 4:3, sized to the request): frames of the synthetic
  camera (:class:`fleetctl.client.syntheticcamera.CameraSequence`: motion, texture, noise),
  frame *seq* of a 15 Hz sequence. The client sends it as video:
  ``foxglove_msgs/msg/CompressedVideo`` carries the source's stamp in ``timestamp`` and
  its ``frame_id``, so the stamp survives encoding.
- ``sensor_msgs/msg/LaserScan``: a realistic scan (:func:`scan_readings`).
- ``std_msgs/msg/String``: ``data`` is JSON ``{"seq": N, "t_ns": T, "pad": "..."}``.

Messages are rosbags objects (the codec's and the CDR serializer's currency), built per type
by a small builder that pads the payload to the requested size.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from fleetctl.client.ros import simworld
from fleetctl.errors import FleetError

Builder = Callable[[Any, int, int, int], Any]  # (typestore, size_bytes, seq, t_ns) -> msg


@dataclass(frozen=True)
class Stamp:
    """What a received test message says about itself."""

    seq: int
    publish_time_ns: int


def _header(ts: Any, seq: int, t_ns: int) -> Any:
    time_cls = ts.types["builtin_interfaces/msg/Time"]
    header_cls = ts.types["std_msgs/msg/Header"]
    stamp = time_cls(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
    return header_cls(stamp=stamp, frame_id=str(seq))


def _laser_scan(ts: Any, size_bytes: int, seq: int, t_ns: int) -> Any:
    n = max(1, size_bytes // 8)  # float32 ranges + intensities
    ranges, intensities = scan_readings(n, seq)
    increment = SCAN_FIELD_RAD / n
    return ts.types["sensor_msgs/msg/LaserScan"](
        header=_header(ts, seq, t_ns), angle_min=SCAN_ANGLE_MIN_RAD,
        angle_max=SCAN_ANGLE_MIN_RAD + increment * (n - 1),
        angle_increment=increment, time_increment=0.0, scan_time=0.1,
        range_min=0.1, range_max=30.0, ranges=ranges, intensities=intensities,
    )


# A 270-degree 2D lidar (Hokuyo UTM-30LX-like).
SCAN_FIELD_RAD = 1.5 * math.pi
SCAN_ANGLE_MIN_RAD = -SCAN_FIELD_RAD / 2
_SCAN_RATE_HZ = 10.0
_RANGE_NOISE_M = 0.01  # the UTM-30LX's repeatability (1 sigma)
_NO_RETURN_FRACTION = 0.01  # beams with no echo: +inf (REP 117)


def scan_readings(beams: int, seq: int) -> tuple[np.ndarray, np.ndarray]:
    """Ranges and intensities (float32) of scan *seq* of a robot driving through a room.

    What a real 2D lidar sends, so that byte counts and compression measured with it mean
    something (a constant scan compresses to nothing; uniform random floats not at all):
    the demo's room and circling robot (:mod:`fleetctl.client.ros.simworld`), range noise
    of 1 cm, ranges in whole millimetres and intensities in whole counts (as the sensor
    reports them), 1 % of beams without a return. Deterministic in *seq*.
    """
    room, motion = simworld.RoomConfig(), simworld.MotionConfig()
    phase = seq / _SCAN_RATE_HZ * motion.speed_m_s / motion.circle_radius_m
    state = simworld.start_state(room, motion, phase_rad=phase)
    true = simworld.laser_ranges(state, room, beams, SCAN_ANGLE_MIN_RAD,
                                 SCAN_FIELD_RAD / beams)
    rng = np.random.default_rng(seq)
    ranges = np.round((true + rng.normal(0.0, _RANGE_NOISE_M, beams)) * 1000.0) / 1000.0
    ranges[rng.random(beams) < _NO_RETURN_FRACTION] = np.inf
    counts = np.round(6000.0 / (1.0 + true) + rng.normal(0.0, 40.0, beams))
    return ranges.astype(np.float32), np.clip(counts, 0.0, 65535.0).astype(np.float32)


def _pose(ts: Any, size_bytes: int, seq: int, t_ns: int) -> Any:
    del size_bytes  # fixed size: a pose is a pose
    point = ts.types["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.0)
    quat = ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    pose = ts.types["geometry_msgs/msg/Pose"](position=point, orientation=quat)
    return ts.types["geometry_msgs/msg/PoseStamped"](header=_header(ts, seq, t_ns), pose=pose)


# Payloads are as compressible as the real thing: a JPEG's bytes are random to deflate,
# a lidar's float32 points shrink ~10 %. Constant bytes compressed to nothing once the
# robot deflated everything on a slow link (docs/wire.md, "Uplink deflate"), and the
# ramp's camera then had the link to itself instead of sharing it. A few variants,
# rotating by seq, made once per size.
_VARIANTS = 8


@functools.lru_cache(maxsize=2 * _VARIANTS)
def _random_bytes(size_bytes: int, variant: int) -> np.ndarray[Any, Any]:
    return np.random.default_rng(variant).integers(0, 256, size_bytes, dtype=np.uint8)


@functools.lru_cache(maxsize=2 * _VARIANTS)
def _lidar_points(points: int, variant: int) -> np.ndarray[Any, Any]:
    xyz = np.random.default_rng(variant).normal(0.0, 10.0, (points, 3)).astype(np.float32)
    return xyz.view(np.uint8).reshape(-1)


def _compressed_image(ts: Any, size_bytes: int, seq: int, t_ns: int) -> Any:
    return ts.types["sensor_msgs/msg/CompressedImage"](
        header=_header(ts, seq, t_ns), format="jpeg",
        data=_random_bytes(size_bytes, seq % _VARIANTS),
    )


def _point_cloud(ts: Any, size_bytes: int, seq: int, t_ns: int) -> Any:
    field_cls = ts.types["sensor_msgs/msg/PointField"]
    fields = [field_cls(name=axis, offset=4 * i, datatype=7, count=1)  # 7 = FLOAT32
              for i, axis in enumerate("xyz")]
    points = max(1, size_bytes // 12)
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=_header(ts, seq, t_ns), height=1, width=points, fields=fields,
        is_bigendian=False, point_step=12, row_step=12 * points,
        data=_lidar_points(points, seq % _VARIANTS), is_dense=True,
    )


CAMERA_FPS = 15.0  # the motion's time base: frame seq shows time seq / 15 s


@functools.lru_cache(maxsize=2)
def _camera(width: int, height: int) -> Any:
    from fleetctl.client.syntheticcamera import CameraSequence

    # A bank of noise fields: fresh noise per frame would cost ~10 ms of the robot's CPU.
    return CameraSequence(width, height, CAMERA_FPS, noise_bank=8)


def camera_size(size_bytes: int) -> tuple[int, int]:
    """The 4:3 rgb8 frame (even width and height) closest to *size_bytes*."""
    width = max(16, 2 * round(math.sqrt(size_bytes / 3 * 4 / 3) / 2))
    return width, max(12, 2 * round(width * 3 / 4 / 2))


def _image(ts: Any, size_bytes: int, seq: int, t_ns: int) -> Any:
    width, height = camera_size(size_bytes)
    pixels = _camera(width, height).frame(seq)
    return ts.types["sensor_msgs/msg/Image"](
        header=_header(ts, seq, t_ns), height=height, width=width, encoding="rgb8",
        is_bigendian=0, step=3 * width, data=pixels.reshape(-1))


def _string(ts: Any, size_bytes: int, seq: int, t_ns: int) -> Any:
    body = {"seq": seq, "t_ns": t_ns, "pad": ""}
    pad = max(0, size_bytes - len(json.dumps(body)))
    body["pad"] = "x" * pad
    return ts.types["std_msgs/msg/String"](data=json.dumps(body))


BUILDERS: dict[str, Builder] = {
    "sensor_msgs/msg/LaserScan": _laser_scan,
    "geometry_msgs/msg/PoseStamped": _pose,
    "sensor_msgs/msg/CompressedImage": _compressed_image,
    "sensor_msgs/msg/Image": _image,
    "sensor_msgs/msg/PointCloud2": _point_cloud,
    "std_msgs/msg/String": _string,
}


def build(ts: Any, type_name: str, size_bytes: int, seq: int, t_ns: int) -> Any:
    """A rosbags message of *type_name*, about *size_bytes* long, stamped (*seq*, *t_ns*).

    Raises:
        FleetError: no builder for *type_name*.
    """
    builder = BUILDERS.get(type_name)
    if builder is None:
        raise FleetError(f"e2e load: no test message builder for {type_name}; "
                         f"choose from {sorted(BUILDERS)}")
    return builder(ts, size_bytes, seq, t_ns)


@dataclass(frozen=True)
class _VideoHeader:
    stamp: Any
    frame_id: str


def read_stamp(msg: Any) -> Stamp:
    """The (seq, publish time) a test message carries.

    Raises:
        FleetError: the message carries no readable stamp (not made by :func:`build`).
    """
    try:
        header = getattr(msg, "header", None)
        if header is None and hasattr(msg, "timestamp"):  # CompressedVideo: the source's
            header = _VideoHeader(msg.timestamp, msg.frame_id)
        if header is not None:
            ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
            return Stamp(int(header.frame_id), ns)
        body = json.loads(msg.data)
        return Stamp(int(body["seq"]), int(body["t_ns"]))
    except (AttributeError, KeyError, TypeError, ValueError) as exc:
        raise FleetError(f"not an e2e test message: {exc}") from exc
