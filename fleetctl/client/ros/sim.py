"""A simulated mobile robot as a real rclpy node (what ``fleetctl demo`` drives).

It publishes the default robot topics of docs/design.md section 7 with realistic sizes and
rates, and obeys ``/goal_pose`` / ``/initialpose`` so a browser operator sees it react:

| topic | type | rate |
|---|---|---|
| ``/scan`` | sensor_msgs/msg/LaserScan, 720 beams | 10 Hz |
| ``/odom`` | nav_msgs/msg/Odometry | 20 Hz |
| ``/pose`` | geometry_msgs/msg/PoseWithCovarianceStamped | 10 Hz |
| ``/camera/image/compressed`` | sensor_msgs/msg/CompressedImage, JPEG 640x480 | 2 Hz |
| ``/points`` | sensor_msgs/msg/PointCloud2, xyz float32, 20k points | 5 Hz |
| ``/battery`` | sensor_msgs/msg/BatteryState | 1 Hz |
| ``/camera/image_raw`` | sensor_msgs/msg/Image, rgb8 640x480 (``raw_camera_hz``) | off |
| ``/events`` | std_msgs/msg/String (no_drop in the client config) | on change, and every 5 s |
| ``/map`` | nav_msgs/msg/OccupancyGrid of the room, 5 cm cells, TRANSIENT_LOCAL | once, at start |
| ``/tf`` | tf2_msgs/msg/TFMessage: ``map -> odom`` (identity), ``odom -> base_link`` | 20 Hz |
| ``/tf_static`` | tf2_msgs/msg/TFMessage: ``camera``, ``imu`` on ``base_link``, latched | once |

``/tf`` and ``/tf_static`` need the ``tf2_msgs`` Python package (apt's ROS, or
scripts/ros_msgs.sh in a venv); without it the sim says so once and publishes no TF.

Each robot runs in its own process with its own ``ROS_DOMAIN_ID``, so two simulated robots on
one machine never see each other's local topics: everything between them goes through the
fleet server.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Quaternion
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy._rclpy_pybind11 import RCLError
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import ok as rclpy_ok
from rclpy.utilities import try_shutdown
from sensor_msgs.msg import BatteryState, CompressedImage, LaserScan, PointCloud2, PointField
from std_msgs.msg import String

from fleetctl.client.ros import simworld
from fleetctl.client.ros.msgtypes import message_class
from fleetctl.errors import ConfigError

_QOS_DEPTH = 10
# As Nav2's map_server and tf2's static broadcaster: the last message kept for late joiners.
_LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
_MAP_MARGIN_M = 1.0
# Where the sim's sensors sit on the robot (m): fixed, so they go to /tf_static.
_STATIC_FRAMES = (("camera", 0.2, 0.0, 0.3), ("imu", 0.0, 0.0, 0.1))
_PHYSICS_HZ = 20.0  # pose integration rate, independent of what is published


@dataclass(frozen=True)
class SimConfig:
    """What one simulated robot publishes, and how often.

    Attributes:
        name: robot name, used for the node name and in log lines.
        phase_rad: where on the default circle the robot starts (rad).
        scan_hz, odom_hz, pose_hz, image_hz, points_hz, battery_hz: publish rates (Hz);
            0 disables that topic.
        events_period_s: period (s) of the heartbeat ``/events`` message; 0 disables it.
        map_resolution_m: cell size (m) of the latched ``/map``; 0 disables it.
        tf_hz: ``/tf`` rate (Hz); 0 disables ``/tf`` and ``/tf_static``.
        raw_camera_hz: rate (Hz) of ``/camera/image_raw``, a raw rgb8 Image with motion,
            texture and noise (:mod:`fleetctl.client.ros.simcamera`, for video topics);
            0 (the default: it costs ~9 ms of CPU per frame) disables it.
        scan_beams: LaserScan beams over 360 degrees.
        cloud_points: PointCloud2 points.
        image_width_px, image_height_px: camera resolution (pixels).
        room, motion: world geometry and driving behaviour.
    """

    name: str = "robot"
    phase_rad: float = 0.0
    scan_hz: float = 10.0
    odom_hz: float = 20.0
    pose_hz: float = 10.0
    image_hz: float = 2.0
    points_hz: float = 5.0
    battery_hz: float = 1.0
    events_period_s: float = 5.0
    map_resolution_m: float = 0.05
    tf_hz: float = 20.0
    raw_camera_hz: float = 0.0
    scan_beams: int = 720
    cloud_points: int = 20_000
    image_width_px: int = 640
    image_height_px: int = 480
    room: simworld.RoomConfig = field(default_factory=simworld.RoomConfig)
    motion: simworld.MotionConfig = field(default_factory=simworld.MotionConfig)


def _stamp_now() -> Time:
    ns = time.time_ns()
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _yaw_quaternion(yaw_rad: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw_rad / 2), w=math.cos(yaw_rad / 2))


def _quaternion_yaw(q: Quaternion) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


class SimRobot(Node):
    """The simulated robot node: integrates the pose and publishes every sensor on timers."""

    def __init__(self, config: SimConfig, context: Any = None) -> None:
        super().__init__(f"{_node_name(config.name)}_sim", context=context)
        self._config = config
        self._state = simworld.start_state(config.room, config.motion, config.phase_rad)
        # The map/odom frames put the origin at the room's centre (where a map view looks
        # first); the simulation itself works in room coordinates with a corner at 0, 0.
        self._origin_m = (config.room.width_m / 2, config.room.depth_m / 2)
        self._started_s = time.monotonic()
        self._last_step_s = self._started_s
        self._event_count = 0
        self._cloud_world = simworld.room_points(config.room, config.cloud_points)
        self._pub_scan = self.create_publisher(LaserScan, "/scan", _QOS_DEPTH)
        self._pub_odom = self.create_publisher(Odometry, "/odom", _QOS_DEPTH)
        self._pub_pose = self.create_publisher(PoseWithCovarianceStamped, "/pose", _QOS_DEPTH)
        self._pub_image = self.create_publisher(
            CompressedImage, "/camera/image/compressed", _QOS_DEPTH
        )
        self._pub_points = self.create_publisher(PointCloud2, "/points", _QOS_DEPTH)
        self._pub_battery = self.create_publisher(BatteryState, "/battery", _QOS_DEPTH)
        # no_drop topics keep a deeper history so a slow bridge start loses nothing.
        self._pub_events = self.create_publisher(String, "/events", 100)
        self.create_subscription(PoseStamped, "/goal_pose", self._on_goal, _QOS_DEPTH)
        self.create_subscription(
            PoseWithCovarianceStamped, "/initialpose", self._on_initialpose, _QOS_DEPTH
        )
        self.create_timer(1.0 / _PHYSICS_HZ, self._step)
        self._every(config.odom_hz, self._publish_odom)
        self._every(config.scan_hz, self._publish_scan)
        self._every(config.pose_hz, self._publish_pose)
        self._every(config.image_hz, self._publish_image)
        self._every(config.points_hz, self._publish_points)
        self._every(config.battery_hz, self._publish_battery)
        if config.events_period_s > 0:
            self.create_timer(config.events_period_s, self._heartbeat)
        if config.map_resolution_m > 0:
            self._pub_map = self.create_publisher(OccupancyGrid, "/map", _LATCHED)
            self._pub_map.publish(self._room_map())
        self._tf_class = self._tf_message_class() if config.tf_hz > 0 else None
        if self._tf_class is not None:
            self._pub_tf = self.create_publisher(self._tf_class, "/tf", 100)
            self._pub_tf_static = self.create_publisher(self._tf_class, "/tf_static", _LATCHED)
            self._pub_tf_static.publish(self._tf_class(transforms=[
                self._transform("base_link", child, x, y, z, 0.0)
                for child, x, y, z in _STATIC_FRAMES]))
            self._every(config.tf_hz, self._publish_tf)
        if config.raw_camera_hz > 0:
            from fleetctl.client.ros.simcamera import SimCamera

            SimCamera(self, "/camera/image_raw", config.raw_camera_hz,
                      config.image_width_px, config.image_height_px)
        # Announce the start once someone listens: /events is volatile, so an event
        # published before the client's subscription matched would reach nobody.
        self._announce = self.create_timer(0.1, self._announce_start)

    def _announce_start(self) -> None:
        if self._pub_events.get_subscription_count() > 0:
            self.publish_event(f"{self._config.name} started")
            self._announce.cancel()
            self.destroy_timer(self._announce)

    def _every(self, rate_hz: float, callback: Callable[[], None]) -> None:
        if rate_hz > 0:
            self.create_timer(1.0 / rate_hz, callback)

    # --- commands ---------------------------------------------------------------------------

    def _on_goal(self, msg: PoseStamped) -> None:
        goal = (float(msg.pose.position.x), float(msg.pose.position.y))
        self._state.goal = (goal[0] + self._origin_m[0], goal[1] + self._origin_m[1])
        self.get_logger().info(f"goal_pose received: x={goal[0]:.2f} m y={goal[1]:.2f} m")
        self.publish_event(f"goal received x={goal[0]:.2f} y={goal[1]:.2f}")

    def _on_initialpose(self, msg: PoseWithCovarianceStamped) -> None:
        pose = msg.pose.pose
        x_m, y_m = float(pose.position.x), float(pose.position.y)
        self._state.x_m, self._state.y_m = x_m + self._origin_m[0], y_m + self._origin_m[1]
        self._state.yaw_rad = _quaternion_yaw(pose.orientation)
        self._state.goal = None
        self.get_logger().info(f"initialpose received: x={x_m:.2f} m y={y_m:.2f} m")
        self.publish_event(f"initialpose set x={x_m:.2f} y={y_m:.2f}")

    def publish_event(self, text: str) -> None:
        """Publish one ``/events`` String (the demo's no_drop topic)."""
        self._event_count += 1
        self._pub_events.publish(String(data=f"[{self._event_count}] {text}"))

    def _heartbeat(self) -> None:
        self.publish_event(f"{self._config.name} alive")

    # --- map and TF ---------------------------------------------------------------------------

    def _room_map(self) -> OccupancyGrid:
        room, res = self._config.room, self._config.map_resolution_m
        cells = simworld.room_grid(room, res, _MAP_MARGIN_M)
        msg = OccupancyGrid()
        msg.header.stamp = _stamp_now()
        msg.header.frame_id = "map"
        msg.info.map_load_time = msg.header.stamp
        msg.info.resolution = res
        msg.info.height, msg.info.width = cells.shape
        # Room coordinates minus the origin offset: map frame has the room's centre at 0.
        msg.info.origin.position.x = -_MAP_MARGIN_M - self._origin_m[0]
        msg.info.origin.position.y = -_MAP_MARGIN_M - self._origin_m[1]
        msg.info.origin.orientation.w = 1.0
        msg.data = cells.reshape(-1).tolist()
        return msg

    def _tf_message_class(self) -> Any:
        try:
            return message_class("tf2_msgs/msg/TFMessage")
        except ConfigError as exc:
            self.get_logger().warning(f"no /tf and /tf_static: {exc}")
            return None

    def _transform(self, parent: str, child: str, x: float, y: float, z: float,
                   yaw: float) -> Any:
        from geometry_msgs.msg import TransformStamped

        t = TransformStamped()
        t.header.stamp = _stamp_now()
        t.header.frame_id, t.child_frame_id = parent, child
        t.transform.translation.x, t.transform.translation.y = x, y
        t.transform.translation.z = z
        t.transform.rotation = _yaw_quaternion(yaw)
        return t

    def _publish_tf(self) -> None:
        assert self._tf_class is not None
        self._pub_tf.publish(self._tf_class(transforms=[
            self._transform("map", "odom", 0.0, 0.0, 0.0, 0.0),
            self._transform("odom", "base_link", self._state.x_m - self._origin_m[0],
                            self._state.y_m - self._origin_m[1], 0.0, self._state.yaw_rad),
        ]))

    # --- sensors ----------------------------------------------------------------------------

    def _step(self) -> None:
        now_s = time.monotonic()
        if self._state.step(now_s - self._last_step_s, self._config.room, self._config.motion):
            self.get_logger().info("goal reached")
            self.publish_event("goal reached")
        self._last_step_s = now_s

    def _publish_odom(self) -> None:
        msg = Odometry()
        msg.header.stamp = _stamp_now()
        msg.header.frame_id = "odom"
        msg.child_frame_id = "base_link"
        msg.pose.pose.position.x = self._state.x_m - self._origin_m[0]
        msg.pose.pose.position.y = self._state.y_m - self._origin_m[1]
        msg.pose.pose.orientation = _yaw_quaternion(self._state.yaw_rad)
        msg.twist.twist.linear.x = self._state.linear_m_s
        msg.twist.twist.angular.z = self._state.angular_rad_s
        self._pub_odom.publish(msg)

    def _publish_pose(self) -> None:
        msg = PoseWithCovarianceStamped()
        msg.header.stamp = _stamp_now()
        msg.header.frame_id = "map"
        msg.pose.pose.position.x = self._state.x_m - self._origin_m[0]
        msg.pose.pose.position.y = self._state.y_m - self._origin_m[1]
        msg.pose.pose.orientation = _yaw_quaternion(self._state.yaw_rad)
        cov = np.zeros(36)
        cov[0] = cov[7] = 0.01  # 10 cm standard deviation in x and y
        cov[35] = 0.005
        msg.pose.covariance = cov
        self._pub_pose.publish(msg)

    def _publish_scan(self) -> None:
        beams = self._config.scan_beams
        increment = 2 * math.pi / beams
        msg = LaserScan()
        msg.header.stamp = _stamp_now()
        msg.header.frame_id = "base_link"
        msg.angle_min, msg.angle_max = -math.pi, math.pi - increment
        msg.angle_increment = increment
        msg.scan_time = 1.0 / self._config.scan_hz
        msg.range_min, msg.range_max = 0.05, 30.0
        msg.ranges = simworld.laser_ranges(
            self._state, self._config.room, beams, -math.pi, increment
        )
        self._pub_scan.publish(msg)

    def _publish_image(self) -> None:
        msg = CompressedImage()
        msg.header.stamp = _stamp_now()
        msg.header.frame_id = "camera"
        msg.format = "jpeg"
        msg.data = simworld.camera_jpeg(
            self._state, self._config.image_width_px, self._config.image_height_px
        )
        self._pub_image.publish(msg)

    def _publish_points(self) -> None:
        xyz = simworld.points_in_robot_frame(self._cloud_world, self._state)
        msg = PointCloud2()
        msg.header.stamp = _stamp_now()
        msg.header.frame_id = "base_link"
        msg.height, msg.width = 1, xyz.shape[0]
        msg.fields = [
            PointField(name=axis, offset=4 * i, datatype=PointField.FLOAT32, count=1)
            for i, axis in enumerate("xyz")
        ]
        msg.is_bigendian = False
        msg.point_step, msg.row_step = 12, 12 * xyz.shape[0]
        msg.is_dense = True
        msg.data = xyz.tobytes()
        self._pub_points.publish(msg)

    def _publish_battery(self) -> None:
        msg = BatteryState()
        msg.header.stamp = _stamp_now()
        msg.percentage = simworld.battery_fraction(time.monotonic() - self._started_s)
        msg.voltage = 22.0 + 3.0 * msg.percentage
        msg.present = True
        self._pub_battery.publish(msg)


def _node_name(robot_name: str) -> str:
    """A valid ROS node name from a robot name (letters, digits and underscores only)."""
    cleaned = "".join(ch if ch.isalnum() else "_" for ch in robot_name)
    return cleaned if cleaned[:1].isalpha() else f"r_{cleaned}"


def run_sim(config: SimConfig) -> None:
    """Run one simulated robot until SIGINT/SIGTERM; rclpy's handlers end the spin cleanly."""
    rclpy.init()
    node = SimRobot(config)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    node.get_logger().info(f"simulated robot {config.name!r} running")
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        # A timer that fired while the signal handler was invalidating the context fails
        # to publish; that is the shutdown we asked for, anything else is a real error.
        if rclpy_ok():
            raise
    finally:
        executor.shutdown()
        node.destroy_node()
        try_shutdown()
