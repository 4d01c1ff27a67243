"""TF bandwidth: every /tf message relayed as is vs the client's TF republisher.

Usage::

    .venv/bin/python benchmarks/media/tf.py [--duration 60]

The case of the Robot Web Tools paper (section IV-A, Fig. 3): a mobile base with a 6-DOF
arm, 52 frames, base and arm teleoperated for a minute; tf2_web_republisher at 10 Hz with
deltas of 0.01 m and 0.01 rad took 208.5 KB/s of ROS TF down to 96.0 KB/s.

The robot here (pure Python, no ROS; the same every run, seeded):

- 52 frames: ``map``, ``odom``, ``base_footprint``, ``base_link``, 4 wheels, a 6-DOF arm
  with a 2-finger gripper (15 frames), a pan/tilt head (2), 26 fixed sensor/mount frames.
- ``/tf``: odometry ``odom -> base_footprint`` at 50 Hz, localization ``map -> odom`` at
  20 Hz (small corrections), and robot_state_publisher's 14 movable joints (4 wheels, 6
  arm joints, 2 fingers, pan, tilt) at the joint_states rate of 50 Hz, every joint in
  every message whether it moved or not, as robot_state_publisher does; joint encoders
  carry 0.2 mrad of noise.
- ``/tf_static``: the 35 fixed joints, one latched message (sent once by both).
- Motion, in a 20 s cycle: drive 0.5 m/s and turn (wheels spin at ~3 rad/s), stop and
  move the arm (up to 0.45 rad/s per joint) while the gripper opens and closes three
  times and the head tilts, then drive while the head pans; every move starts and ends
  at rest; ``map -> odom`` drifts by a few mm per second.

Both sides are measured as what goes on the wire: every message is a fleetctl frame
encoded by :class:`fleetctl.wire.codec.Codec` (metadata included). "Raw" is what a
``publish`` entry for ``/tf`` sends (every message); "republished" is
:class:`fleetctl.client.tfthrottle.TfThrottle` at its defaults (10 Hz, 0.01 m, 0.01 rad),
polled after each /tf message and on a 10 Hz timer, as the client does. The receiver of
the republished stream applies each message; right after each one, its pose of every pair
is compared with the robot's newest (the bound the deltas give), and at every /tf message
(the error a viewer may see between two messages). KB = 1000 bytes.
"""

from __future__ import annotations

import argparse
import math
import random
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from fleetctl.client.config import TfSpec
from fleetctl.client.tfthrottle import (
    StaticTf,
    TfThrottle,
    pair_of,
    pose_of,
    rotation_rad,
    translation_m,
)
from fleetctl.wire.codec import Codec, default_codec

TF_TYPE = "tf2_msgs/msg/TFMessage"
TOPIC = "/robot/tf"
STATIC_TOPIC = "/robot/tf_static"
STEP_S = 0.002  # simulation step: every rate below divides 500 Hz
WHEEL_RADIUS_M = 0.165
TRACK_M = 0.55

Vec = tuple[float, float, float]

# (parent, child, origin xyz in the parent (m), axis or None for a fixed joint)
MOVABLE: list[tuple[str, str, Vec, Vec]] = [
    ("base_link", "front_left_wheel", (0.256, 0.285, 0.033), (0, 1, 0)),
    ("base_link", "front_right_wheel", (0.256, -0.285, 0.033), (0, 1, 0)),
    ("base_link", "rear_left_wheel", (-0.256, 0.285, 0.033), (0, 1, 0)),
    ("base_link", "rear_right_wheel", (-0.256, -0.285, 0.033), (0, 1, 0)),
    ("arm_base_link", "shoulder_link", (0.0, 0.0, 0.089), (0, 0, 1)),
    ("shoulder_link", "upper_arm_link", (0.0, 0.136, 0.0), (0, 1, 0)),
    ("upper_arm_link", "forearm_link", (0.0, -0.120, 0.425), (0, 1, 0)),
    ("forearm_link", "wrist_1_link", (0.0, 0.0, 0.392), (0, 1, 0)),
    ("wrist_1_link", "wrist_2_link", (0.0, 0.093, 0.0), (0, 0, 1)),
    ("wrist_2_link", "wrist_3_link", (0.0, 0.0, 0.095), (0, 1, 0)),
    ("gripper_base_link", "left_finger_link", (0.0, 0.03, 0.06), (1, 0, 0)),
    ("gripper_base_link", "right_finger_link", (0.0, -0.03, 0.06), (1, 0, 0)),
    ("head_mount_link", "head_pan_link", (0.0, 0.0, 0.05), (0, 0, 1)),
    ("head_pan_link", "head_tilt_link", (0.0, 0.0, 0.08), (0, 1, 0)),
]
FIXED: list[tuple[str, str, Vec]] = [
    ("base_footprint", "base_link", (0.0, 0.0, 0.13)),
    ("base_link", "chassis_link", (0.0, 0.0, 0.0)),
    ("base_link", "top_plate_link", (0.0, 0.0, 0.225)),
    ("base_link", "front_bumper_link", (0.48, 0.0, 0.091)),
    ("base_link", "rear_bumper_link", (-0.48, 0.0, 0.091)),
    ("base_link", "imu_link", (0.0, 0.0, 0.05)),
    ("base_link", "gps_link", (-0.2, 0.0, 0.6)),
    ("base_link", "estop_link", (-0.3, 0.2, 0.25)),
    ("base_link", "light_link", (0.45, 0.0, 0.2)),
    ("top_plate_link", "user_rail_link", (0.272, 0.0, 0.006)),
    ("top_plate_link", "front_mount", (0.12, 0.0, 0.006)),
    ("top_plate_link", "rear_mount", (-0.12, 0.0, 0.006)),
    ("top_plate_link", "antenna_link", (-0.3, 0.1, 0.1)),
    ("front_mount", "laser_mount", (0.1, 0.0, 0.05)),
    ("laser_mount", "laser", (0.0, 0.0, 0.06)),
    ("front_mount", "front_camera_link", (0.15, 0.0, 0.1)),
    ("front_camera_link", "front_camera_color_frame", (0.0, 0.015, 0.0)),
    ("front_camera_color_frame", "front_camera_color_optical_frame", (0.0, 0.0, 0.0)),
    ("front_camera_link", "front_camera_depth_frame", (0.0, 0.0, 0.0)),
    ("front_camera_depth_frame", "front_camera_depth_optical_frame", (0.0, 0.0, 0.0)),
    ("rear_mount", "arm_mount_link", (0.0, 0.0, 0.01)),
    ("arm_mount_link", "arm_base_link", (0.0, 0.0, 0.02)),
    ("wrist_3_link", "ee_link", (0.0, 0.082, 0.0)),
    ("ee_link", "tool0", (0.0, 0.0, 0.0)),
    ("tool0", "gripper_base_link", (0.0, 0.0, 0.02)),
    ("left_finger_link", "left_fingertip_link", (0.0, 0.0, 0.045)),
    ("right_finger_link", "right_fingertip_link", (0.0, 0.0, 0.045)),
    ("tool0", "wrist_camera_link", (0.05, 0.0, 0.0)),
    ("wrist_camera_link", "wrist_camera_optical_frame", (0.0, 0.0, 0.0)),
    ("top_plate_link", "head_mount_link", (0.2, 0.0, 0.9)),
    ("head_tilt_link", "head_camera_link", (0.05, 0.0, 0.04)),
    ("head_camera_link", "head_camera_rgb_frame", (0.0, 0.02, 0.0)),
    ("head_camera_rgb_frame", "head_camera_rgb_optical_frame", (0.0, 0.0, 0.0)),
    ("head_camera_link", "head_camera_depth_frame", (0.0, -0.02, 0.0)),
    ("head_camera_depth_frame", "head_camera_depth_optical_frame", (0.0, 0.0, 0.0)),
]
FRAME_COUNT = 52


def frames() -> set[str]:
    """Every frame of the robot (52)."""
    names = {"map", "odom", "base_footprint"}
    for parent, child, *_ in MOVABLE + FIXED:  # type: ignore[operator]
        names |= {parent, child}
    return names


def axis_angle(axis: Vec, angle: float) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a rotation by *angle* rad about unit *axis*."""
    s = math.sin(angle / 2)
    return (axis[0] * s, axis[1] * s, axis[2] * s, math.cos(angle / 2))


class MessageBuilder:
    """Builds rosbags TFMessage objects of the codec's registry."""

    def __init__(self, codec: Codec) -> None:
        get = codec.registry.get
        self._tf = get(TF_TYPE).cls
        self._ts = get("geometry_msgs/msg/TransformStamped").cls
        self._header = get("std_msgs/msg/Header").cls
        self._time = get("builtin_interfaces/msg/Time").cls
        self._transform = get("geometry_msgs/msg/Transform").cls
        self._vec = get("geometry_msgs/msg/Vector3").cls
        self._quat = get("geometry_msgs/msg/Quaternion").cls

    def transform(self, t_s: float, parent: str, child: str, xyz: Vec,
                  q: tuple[float, float, float, float]) -> Any:
        stamp = self._time(int(t_s), int((t_s % 1) * 1e9))
        return self._ts(self._header(stamp, parent), child,
                        self._transform(self._vec(*xyz), self._quat(*q)))

    def message(self, transforms: list[Any]) -> Any:
        return self._tf(transforms)


@dataclass
class RobotState:
    """The teleoperated robot's joints and pose at one instant."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    wheel_l: float = 0.0
    wheel_r: float = 0.0
    map_dx: float = 0.0
    map_dyaw: float = 0.0
    arm: tuple[float, ...] = (0.0,) * 6
    fingers: float = 0.0
    pan: float = 0.0
    tilt: float = 0.0


def teleop(state: RobotState, t_s: float, dt_s: float) -> None:
    """Advance *state* by *dt_s* along the 20 s teleoperation cycle (see the docstring)."""
    phase = t_s % 20.0
    v, w = 0.0, 0.0
    if phase < 7.0:
        v, w = 0.5, 0.3 * math.sin(t_s * 0.7)
    elif phase >= 14.0:
        v, w = 0.3, -0.2
        state.pan = 0.8 * math.sin(math.pi * (phase - 14.0) / 6.0)
    else:
        # Each profile starts and ends at rest: teleoperation moves, it does not jump.
        a = (phase - 7.0) / 7.0
        state.arm = tuple(1.0 * (i - 2.5) / 2.5 * math.sin(math.pi * a) for i in range(6))
        state.fingers = 0.02 * math.sin(3 * math.pi * a) ** 2
        state.tilt = 0.3 * math.sin(math.pi * a)
    state.x += v * math.cos(state.yaw) * dt_s
    state.y += v * math.sin(state.yaw) * dt_s
    state.yaw += w * dt_s
    state.wheel_l += (v - w * TRACK_M / 2) / WHEEL_RADIUS_M * dt_s
    state.wheel_r += (v + w * TRACK_M / 2) / WHEEL_RADIUS_M * dt_s
    state.map_dx += 0.003 * dt_s
    state.map_dyaw += 0.0005 * dt_s


def joint_angles(state: RobotState, rng: random.Random) -> list[float]:
    """The 14 movable joints' positions (rad; fingers rotate by their opening), with
    encoder noise."""
    raw = [state.wheel_l, state.wheel_r, state.wheel_l, state.wheel_r, *state.arm,
           state.fingers * 10, -state.fingers * 10, state.pan, state.tilt]
    return [a + rng.gauss(0.0, 0.0002) for a in raw]


@dataclass
class Stream:
    """Bytes and messages sent on one side."""

    bytes: int = 0
    messages: int = 0
    transforms: int = 0


class Receiver:
    """What a viewer of the republished stream holds, and its error vs the robot."""

    def __init__(self) -> None:
        self.poses: dict[tuple[str, str], Any] = {}
        self.max_after_message = (0.0, 0.0)  # (m, rad) right after each message
        self.max_any_time = (0.0, 0.0)  # (m, rad) at every /tf message

    def apply(self, transforms: list[Any]) -> None:
        for t in transforms:
            self.poses[pair_of(t)] = pose_of(t)

    def error(self, truth: dict[tuple[str, str], Any]) -> tuple[float, float]:
        worst_t, worst_r = 0.0, 0.0
        for pair, pose in truth.items():
            held = self.poses.get(pair)
            if held is not None:
                worst_t = max(worst_t, translation_m(held, pose))
                worst_r = max(worst_r, rotation_rad(held, pose))
        return worst_t, worst_r


def _max(a: tuple[float, float], b: tuple[float, float]) -> tuple[float, float]:
    return max(a[0], b[0]), max(a[1], b[1])


def measure_tf(duration_s: float = 60.0, spec: TfSpec | None = None,
               codec: Codec | None = None, seed: int = 1) -> dict[str, Any]:
    """Simulate *duration_s* of the 52-frame robot and measure both streams.

    Args:
        duration_s: Simulated seconds (no wall-clock waiting).
        spec: The republisher's settings (default: the client's defaults).
        codec: The frame codec (default: fleetctl's default registry).
        seed: Seed of the encoder noise.

    Returns:
        A JSON-able dict: ``raw_kBps`` and ``republished_kBps`` (KB = 1000 bytes, frames
        as sent, /tf_static once included), ``ratio``, message and transform rates, the
        max pose error right after each republished message (``max_error_m``,
        ``max_error_rad``, bounded by the deltas) and at any /tf message
        (``max_error_any_time_m``/``_rad``), and the settings.
    """
    spec = spec or TfSpec()
    codec = codec or default_codec()
    build = MessageBuilder(codec)
    rng = random.Random(seed)
    throttle, static = TfThrottle(spec), StaticTf()
    raw, republished, receiver = Stream(), Stream(), Receiver()
    truth: dict[tuple[str, str], Any] = {}
    seq = {"raw": 0, "rep": 0}

    def send(stream: Stream, key: str, topic: str, transforms: list[Any], now_s: float,
             latched: bool = False) -> None:
        seq[key] += 1
        frame = codec.encode(build.message(transforms), TF_TYPE, topic,
                             publish_time_ns=int(now_s * 1e9), seq=seq[key], latched=latched)
        stream.bytes += len(frame)
        stream.messages += 1
        stream.transforms += len(transforms)

    def on_tf(transforms: list[Any], now_s: float) -> None:
        send(raw, "raw", TOPIC, transforms, now_s)
        for t in transforms:
            truth[pair_of(t)] = pose_of(t)
        throttle.offer(transforms)
        tick(now_s)
        receiver.max_any_time = _max(receiver.max_any_time, receiver.error(truth))

    def tick(now_s: float) -> None:
        out = throttle.poll(now_s)
        if out is not None:
            send(republished, "rep", TOPIC, out.transforms, now_s, latched=out.snapshot)
            receiver.apply(out.transforms)
            receiver.max_after_message = _max(receiver.max_after_message,
                                              receiver.error(truth))

    statics = [build.transform(0.0, p, c, xyz, (0.0, 0.0, 0.0, 1.0)) for p, c, xyz in FIXED]
    whole = static.offer(statics)
    assert whole is not None
    for stream, key in ((raw, "raw"), (republished, "rep")):
        send(stream, key, STATIC_TOPIC, statics if key == "raw" else whole, 0.0, latched=True)
    _simulate(duration_s, spec, rng, build, on_tf, tick)
    return _result(duration_s, spec, raw, republished, receiver, len(FIXED))


def _simulate(duration_s: float, spec: TfSpec, rng: random.Random, build: MessageBuilder,
              on_tf: Callable[[list[Any], float], None],
              tick: Callable[[float], None]) -> None:
    """Step the robot at 500 Hz; fire each publisher and the republisher's timer at its
    rate."""
    state = RobotState()
    timer_steps = max(1, round(1.0 / spec.max_rate_hz / STEP_S))
    for k in range(int(duration_s / STEP_S)):
        now = k * STEP_S
        teleop(state, now, STEP_S)
        if k % 10 == 0:  # odometry, 50 Hz
            on_tf([build.transform(now, "odom", "base_footprint", (state.x, state.y, 0.0),
                                   axis_angle((0, 0, 1), state.yaw))], now)
        if k % 25 == 3:  # localization, 20 Hz
            on_tf([build.transform(now, "map", "odom", (state.map_dx, 0.0, 0.0),
                                   axis_angle((0, 0, 1), state.map_dyaw))], now)
        if k % 10 == 5:  # robot_state_publisher, joint_states at 50 Hz
            angles = joint_angles(state, rng)
            on_tf([build.transform(now, p, c, xyz, axis_angle(axis, a))
                   for (p, c, xyz, axis), a in zip(MOVABLE, angles, strict=True)], now)
        if k % timer_steps == 0:
            tick(now)


def _result(duration_s: float, spec: TfSpec, raw: Stream, rep: Stream, receiver: Receiver,
            static_pairs: int) -> dict[str, Any]:
    return {
        "frames": len(frames()),
        "static_pairs": static_pairs,
        "duration_s": duration_s,
        "raw_kBps": raw.bytes / duration_s / 1000,
        "republished_kBps": rep.bytes / duration_s / 1000,
        "ratio": raw.bytes / rep.bytes,
        "raw_messages_per_s": raw.messages / duration_s,
        "republished_messages_per_s": rep.messages / duration_s,
        "raw_transforms_per_s": raw.transforms / duration_s,
        "republished_transforms_per_s": rep.transforms / duration_s,
        "max_error_m": receiver.max_after_message[0],
        "max_error_rad": receiver.max_after_message[1],
        "max_error_any_time_m": receiver.max_any_time[0],
        "max_error_any_time_rad": receiver.max_any_time[1],
        "translation_delta_m": spec.translation_delta_m,
        "rotation_delta_rad": spec.rotation_delta_rad,
        "max_rate_hz": spec.max_rate_hz,
    }


def render(result: dict[str, Any]) -> str:
    """The result as a small text table."""
    r = result
    return "\n".join([
        f"TF, {r['frames']}-frame mobile manipulator, {r['duration_s']:.0f} s teleoperated "
        f"(republisher {r['max_rate_hz']:g} Hz, {r['translation_delta_m']:g} m, "
        f"{r['rotation_delta_rad']:g} rad)",
        f"{'':24}{'KB/s':>10}{'msgs/s':>10}{'tf/s':>10}",
        f"{'raw /tf (every message)':24}{r['raw_kBps']:10.1f}{r['raw_messages_per_s']:10.1f}"
        f"{r['raw_transforms_per_s']:10.1f}",
        f"{'republished':24}{r['republished_kBps']:10.1f}"
        f"{r['republished_messages_per_s']:10.1f}{r['republished_transforms_per_s']:10.1f}",
        f"reduction {r['ratio']:.1f}x (RWT: 208.5 -> 96.0 KB/s, 2.2x)",
        f"max pose error after each message: {r['max_error_m'] * 1000:.2f} mm, "
        f"{r['max_error_rad']:.4f} rad (bound: the deltas); between messages: "
        f"{r['max_error_any_time_m'] * 1000:.1f} mm, {r['max_error_any_time_rad']:.4f} rad",
    ])


def main() -> None:
    """Measure and print."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=60.0, help="simulated seconds")
    args = parser.parse_args()
    print(render(measure_tf(args.duration)))


if __name__ == "__main__":
    main()
