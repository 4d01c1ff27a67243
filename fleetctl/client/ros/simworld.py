"""The simulated world of ``fleetctl demo``'s robots: a rectangular room and a robot in it.

Pure numpy (and Pillow for the camera JPEG): no ROS here, so the geometry is unit-tested
without rclpy. :mod:`fleetctl.client.ros.sim` wraps it in a real rclpy node.

Frames: the room spans ``[0, width_m] x [0, depth_m]`` in room coordinates; the node
publishes ``map``/``odom`` poses with the origin at the room's centre. The robot's sensors
are at its base, x forward, y left, z up.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float32]


@dataclass(frozen=True)
class RoomConfig:
    """A rectangular room with walls ``height_m`` tall.

    Attributes:
        width_m: extent along x (m).
        depth_m: extent along y (m).
        height_m: wall height (m); the point cloud samples walls up to this height.
    """

    width_m: float = 10.0
    depth_m: float = 8.0
    height_m: float = 2.5


@dataclass(frozen=True)
class MotionConfig:
    """How the robot drives when it has no goal: a circle around the room's centre.

    Attributes:
        speed_m_s: forward speed (m/s), also used to drive toward a goal.
        circle_radius_m: radius of the default circle (m).
        goal_tolerance_m: distance (m) at which a goal counts as reached.
        max_turn_rate_rad_s: turn rate limit while heading for a goal (rad/s).
    """

    speed_m_s: float = 0.5
    circle_radius_m: float = 2.0
    goal_tolerance_m: float = 0.15
    max_turn_rate_rad_s: float = 1.5


@dataclass
class RobotState:
    """The robot's planar pose and velocity (mutable: integrated by :meth:`step`).

    Attributes:
        x_m, y_m: position in the room frame (m).
        yaw_rad: heading, counter-clockwise from +x (rad).
        linear_m_s, angular_rad_s: the last commanded velocities.
        goal: ``(x_m, y_m)`` to drive to, or ``None`` to circle.
    """

    x_m: float
    y_m: float
    yaw_rad: float
    linear_m_s: float = 0.0
    angular_rad_s: float = 0.0
    goal: tuple[float, float] | None = None

    def step(self, dt_s: float, room: RoomConfig, motion: MotionConfig) -> bool:
        """Advance the pose by *dt_s* seconds; return True when a goal was just reached."""
        reached = False
        if self.goal is None:
            self.linear_m_s = motion.speed_m_s
            self.angular_rad_s = motion.speed_m_s / motion.circle_radius_m
        else:
            dx, dy = self.goal[0] - self.x_m, self.goal[1] - self.y_m
            if math.hypot(dx, dy) <= motion.goal_tolerance_m:
                self.goal, reached = None, True
                self.linear_m_s = self.angular_rad_s = 0.0
            else:
                error = _wrap(math.atan2(dy, dx) - self.yaw_rad)
                limit = motion.max_turn_rate_rad_s
                self.angular_rad_s = max(-limit, min(limit, 2.0 * error))
                # Turn on the spot first when facing away, so the robot never leaves the room.
                self.linear_m_s = motion.speed_m_s * max(0.0, math.cos(error))
        self.yaw_rad = _wrap(self.yaw_rad + self.angular_rad_s * dt_s)
        self.x_m += self.linear_m_s * math.cos(self.yaw_rad) * dt_s
        self.y_m += self.linear_m_s * math.sin(self.yaw_rad) * dt_s
        # Clamp inside the walls: a goal outside the room must not teleport through them.
        self.x_m = min(max(self.x_m, 0.05), room.width_m - 0.05)
        self.y_m = min(max(self.y_m, 0.05), room.depth_m - 0.05)
        return reached


def start_state(room: RoomConfig, motion: MotionConfig, phase_rad: float) -> RobotState:
    """A robot on the default circle at angle *phase_rad*, heading tangentially."""
    cx, cy = room.width_m / 2, room.depth_m / 2
    return RobotState(
        x_m=cx + motion.circle_radius_m * math.cos(phase_rad),
        y_m=cy + motion.circle_radius_m * math.sin(phase_rad),
        yaw_rad=_wrap(phase_rad + math.pi / 2),
    )


def _wrap(angle_rad: float) -> float:
    return math.atan2(math.sin(angle_rad), math.cos(angle_rad))


def laser_ranges(
    state: RobotState, room: RoomConfig, count: int, angle_min_rad: float, increment_rad: float
) -> FloatArray:
    """Distances (m) from the robot to the room's walls along *count* beams.

    Beam i points at ``yaw + angle_min_rad + i * increment_rad``. Vectorised: one numpy pass
    for the whole scan.
    """
    angles = state.yaw_rad + angle_min_rad + increment_rad * np.arange(count, dtype=np.float64)
    dx, dy = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(dx > 0, (room.width_m - state.x_m) / dx, -state.x_m / dx)
        ty = np.where(dy > 0, (room.depth_m - state.y_m) / dy, -state.y_m / dy)
    tx = np.where(np.isfinite(tx) & (tx >= 0), tx, np.inf)
    ty = np.where(np.isfinite(ty) & (ty >= 0), ty, np.inf)
    return np.minimum(tx, ty).astype(np.float32)


def room_points(room: RoomConfig, count: int, seed: int = 0) -> FloatArray:
    """*count* points (N x 3, m) sampled uniformly on the room's four walls, in the room frame."""
    rng = np.random.default_rng(seed)
    perimeter = 2 * (room.width_m + room.depth_m)
    s = rng.uniform(0.0, perimeter, count)
    z = rng.uniform(0.0, room.height_m, count)
    w, d = room.width_m, room.depth_m
    x = np.select(
        [s < w, s < w + d, s < 2 * w + d],
        [s, np.full(count, w), 2 * w + d - s],
        np.zeros(count),
    )
    y = np.select(
        [s < w, s < w + d, s < 2 * w + d],
        [np.zeros(count), s - w, np.full(count, d)],
        perimeter - s,
    )
    return np.stack([x, y, z], axis=1).astype(np.float32)


def points_in_robot_frame(points: FloatArray, state: RobotState) -> FloatArray:
    """Transform room-frame points (N x 3, m) into the robot frame (x forward, y left)."""
    c, s = math.cos(state.yaw_rad), math.sin(state.yaw_rad)
    dx = points[:, 0] - state.x_m
    dy = points[:, 1] - state.y_m
    out = np.empty_like(points)
    out[:, 0] = c * dx + s * dy
    out[:, 1] = -s * dx + c * dy
    out[:, 2] = points[:, 2]
    return out


def camera_jpeg(state: RobotState, width_px: int, height_px: int, quality: int = 75) -> bytes:
    """A JPEG (bytes) of a synthetic camera view: a heading-dependent colour gradient.

    The image changes with the robot's heading, so a viewer can see frames move.

    Raises:
        ImportError: Pillow is not installed (the ``ros`` extra depends on it).
    """
    from PIL import Image  # deferred: only the camera needs Pillow

    hue = (state.yaw_rad + math.pi) / (2 * math.pi)
    cols = np.linspace(0.0, 1.0, width_px, dtype=np.float32)
    rows = np.linspace(0.0, 1.0, height_px, dtype=np.float32)[:, None]
    shift = (cols[None, :] + hue) % 1.0
    rgb = np.empty((height_px, width_px, 3), dtype=np.uint8)
    rgb[..., 0] = (255 * shift).astype(np.uint8)
    rgb[..., 1] = (255 * rows).astype(np.uint8)
    rgb[..., 2] = (255 * (1.0 - shift * rows)).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(rgb).save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()


# ROS OccupancyGrid cell values.
UNKNOWN, FREE, OCCUPIED = -1, 0, 100


def room_grid(room: RoomConfig, resolution_m: float, margin_m: float = 1.0) -> npt.NDArray[np.int8]:
    """The room as an occupancy grid (rows along y, columns along x; int8 ROS values).

    The grid covers the room plus *margin_m* on every side: unknown outside, occupied on
    the walls (one cell thick, where the laser hits), free inside. Cell (row 0, col 0) is
    at room coordinates ``(-margin_m, -margin_m)``.
    """
    cols = math.ceil((room.width_m + 2 * margin_m) / resolution_m)
    rows = math.ceil((room.depth_m + 2 * margin_m) / resolution_m)
    cells = np.full((rows, cols), UNKNOWN, dtype=np.int8)
    x0, y0 = (round(margin_m / resolution_m) for _ in range(2))
    x1 = x0 + round(room.width_m / resolution_m)
    y1 = y0 + round(room.depth_m / resolution_m)
    cells[y0:y1 + 1, x0:x1 + 1] = OCCUPIED
    cells[y0 + 1:y1, x0 + 1:x1] = FREE
    return cells


def battery_fraction(elapsed_s: float, full_runtime_s: float = 3600.0) -> float:
    """Charge in [0.05, 1]: drains linearly over *full_runtime_s*, then recharges (a sawtooth)."""
    return 1.0 - 0.95 * ((elapsed_s / full_runtime_s) % 1.0)
