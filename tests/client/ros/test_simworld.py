"""Unit tests of the simulated world's geometry (no ROS needed)."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

from fleetctl.client.ros import simworld

ROOM = simworld.RoomConfig(width_m=10.0, depth_m=8.0, height_m=2.5)
MOTION = simworld.MotionConfig()


def test_laser_ranges_hit_the_walls_at_the_right_distances() -> None:
    state = simworld.RobotState(x_m=3.0, y_m=2.0, yaw_rad=0.0)
    # Four beams: forward (+x), left (+y), back (-x), right (-y).
    ranges = simworld.laser_ranges(state, ROOM, 4, 0.0, math.pi / 2)
    assert ranges.dtype == np.float32
    np.testing.assert_allclose(ranges, [7.0, 6.0, 3.0, 2.0], rtol=1e-6)


def test_laser_ranges_follow_the_heading() -> None:
    state = simworld.RobotState(x_m=3.0, y_m=2.0, yaw_rad=math.pi / 2)
    forward = simworld.laser_ranges(state, ROOM, 1, 0.0, 0.1)
    assert forward[0] == pytest.approx(6.0)


def test_laser_ranges_are_finite_for_a_full_scan() -> None:
    state = simworld.start_state(ROOM, MOTION, 0.3)
    ranges = simworld.laser_ranges(state, ROOM, 720, -math.pi, 2 * math.pi / 720)
    assert ranges.shape == (720,)
    assert np.all(np.isfinite(ranges))
    assert np.all(ranges > 0)
    assert ranges.max() <= math.hypot(ROOM.width_m, ROOM.depth_m)


def test_circle_keeps_the_robot_on_its_radius() -> None:
    state = simworld.start_state(ROOM, MOTION, 0.0)
    for _ in range(400):
        state.step(0.05, ROOM, MOTION)
    radius = math.hypot(state.x_m - 5.0, state.y_m - 4.0)
    assert radius == pytest.approx(MOTION.circle_radius_m, abs=0.1)


def test_goal_is_reached_then_cleared() -> None:
    state = simworld.RobotState(x_m=2.0, y_m=2.0, yaw_rad=math.pi, goal=(6.0, 5.0))
    steps = 0
    while not state.step(0.05, ROOM, MOTION):
        steps += 1
        assert steps < 1000, "goal not reached in 50 simulated seconds"
    assert state.goal is None
    assert math.hypot(state.x_m - 6.0, state.y_m - 5.0) < 0.3


def test_goal_outside_the_room_never_leaves_it() -> None:
    state = simworld.RobotState(x_m=5.0, y_m=4.0, yaw_rad=0.0, goal=(50.0, -20.0))
    for _ in range(2000):
        state.step(0.05, ROOM, MOTION)
        assert 0.0 < state.x_m < ROOM.width_m
        assert 0.0 < state.y_m < ROOM.depth_m


def test_room_points_lie_on_the_walls() -> None:
    points = simworld.room_points(ROOM, 5000)
    assert points.shape == (5000, 3)
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    on_wall = (
        np.isclose(x, 0, atol=1e-4)
        | np.isclose(x, ROOM.width_m, atol=1e-4)
        | np.isclose(y, 0, atol=1e-4)
        | np.isclose(y, ROOM.depth_m, atol=1e-4)
    )
    assert on_wall.all()
    assert (z >= 0).all() and (z <= ROOM.height_m).all()


def test_points_in_robot_frame_rotates_and_translates() -> None:
    state = simworld.RobotState(x_m=1.0, y_m=1.0, yaw_rad=math.pi / 2)
    world = np.array([[1.0, 3.0, 0.5], [2.0, 1.0, 0.0]], dtype=np.float32)
    local = simworld.points_in_robot_frame(world, state)
    np.testing.assert_allclose(local, [[2.0, 0.0, 0.5], [0.0, -1.0, 0.0]], atol=1e-6)


def test_camera_jpeg_is_a_valid_image_of_the_requested_size() -> None:
    from PIL import Image

    data = simworld.camera_jpeg(simworld.RobotState(1.0, 1.0, 0.5), 640, 480)
    assert data[:2] == b"\xff\xd8"
    with Image.open(io.BytesIO(data)) as image:
        assert image.format == "JPEG"
        assert image.size == (640, 480)


def test_battery_is_a_bounded_sawtooth() -> None:
    assert simworld.battery_fraction(0.0) == pytest.approx(1.0)
    assert simworld.battery_fraction(1800.0) == pytest.approx(0.525)
    assert 0.05 <= simworld.battery_fraction(3599.0) < 0.06
    assert simworld.battery_fraction(3600.0) == pytest.approx(1.0)


def test_room_grid_has_walls_free_inside_unknown_outside() -> None:
    from fleetctl.client.ros.simworld import FREE, OCCUPIED, UNKNOWN, room_grid

    cells = room_grid(simworld.RoomConfig(width_m=2.0, depth_m=1.0), 0.5, margin_m=0.5)
    assert cells.shape == (4, 6)
    assert cells.tolist() == [
        [UNKNOWN] * 6,
        [UNKNOWN] + [OCCUPIED] * 5,
        [UNKNOWN, OCCUPIED, FREE, FREE, FREE, OCCUPIED],
        [UNKNOWN] + [OCCUPIED] * 5,
    ]
