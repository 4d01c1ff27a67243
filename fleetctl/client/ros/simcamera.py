"""A simulated raw camera: ``sensor_msgs/msg/Image``, 640x480 rgb8 at 30 Hz, as a driver sends.

The pictures are :class:`fleetctl.client.syntheticcamera.CameraSequence`'s: a pan and zoom
across photographs with sensor noise, so video encoding meets what a real camera gives it
(motion, texture, noise), not a static or flat frame. Noise comes from a bank of pre-drawn
fields (``noise_bank=8``) to keep a 30 Hz camera at ~9 ms of CPU per frame.

:class:`SimCamera` attaches a publisher and a timer to any node (the simulated robot's, see
``SimConfig.raw_camera_hz`` in :mod:`fleetctl.client.ros.sim`); ``python -m
fleetctl.client.ros.simcamera [TOPIC] [RATE_HZ]`` runs one alone in its own node (tests).
Messages are serialized with rosbags and published as CDR bytes: building an rclpy Image
from 921,600 Python ints would cost more than the picture.
"""

from __future__ import annotations

import sys
import time
from typing import Any

from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image as RosImage

from fleetctl.client.syntheticcamera import CameraSequence

__all__ = ["SimCamera", "main"]

IMAGE_TYPE = "sensor_msgs/msg/Image"
# What camera drivers use (image_transport's sensor data profile): a late frame is useless.
CAMERA_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.BEST_EFFORT)


class SimCamera:
    """Publishes the synthetic camera on *topic* from *node*'s executor.

    Args:
        node: The node that owns the publisher and the timer.
        topic: Image topic.
        rate_hz: Frame rate (Hz).
        width: Image width in pixels.
        height: Image height in pixels.
        frame_id: The images' header frame_id.
    """

    def __init__(self, node: Node, topic: str = "/camera/image_raw", rate_hz: float = 30.0,
                 width: int = 640, height: int = 480, frame_id: str = "camera") -> None:
        from rosbags.typesys import Stores, get_typestore

        self._typestore = get_typestore(Stores.ROS2_JAZZY)
        self._image_cls = self._typestore.types[IMAGE_TYPE]
        self._time_cls = self._typestore.types["builtin_interfaces/msg/Time"]
        self._header_cls = self._typestore.types["std_msgs/msg/Header"]
        self._sequence = CameraSequence(width, height, rate_hz, noise_bank=8)
        self._frame_id = frame_id
        self._rate_hz = rate_hz
        self._started_s = time.monotonic()
        self.published = 0
        self._publisher = node.create_publisher(RosImage, topic, CAMERA_QOS)
        node.create_timer(1.0 / rate_hz, self.publish)

    def publish(self) -> None:
        """Publish the frame of the current time (a late timer skips frames, as a camera
        does, instead of slowing the motion down)."""
        index = round((time.monotonic() - self._started_s) * self._rate_hz)
        self._publisher.publish(self.cdr(index, time.time_ns()))
        self.published += 1

    def cdr(self, index: int, stamp_ns: int) -> bytes:
        """Frame *index* as a serialized ``sensor_msgs/msg/Image`` stamped *stamp_ns*."""
        pixels = self._sequence.frame(index)
        height, width = pixels.shape[:2]
        stamp = self._time_cls(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        msg = self._image_cls(
            header=self._header_cls(stamp=stamp, frame_id=self._frame_id), height=height,
            width=width, encoding="rgb8", is_bigendian=0, step=3 * width,
            data=pixels.reshape(-1))
        return bytes(self._typestore.serialize_cdr(msg, IMAGE_TYPE))


def main(argv: list[str]) -> None:
    """``python -m fleetctl.client.ros.simcamera [TOPIC] [RATE_HZ] [WIDTHxHEIGHT]``: run
    until SIGINT or SIGTERM (``ROS_DOMAIN_ID`` from the environment)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.utilities import try_shutdown

    topic = argv[0] if argv else "/camera/image_raw"
    rate_hz = float(argv[1]) if len(argv) > 1 else 30.0
    width, height = _size(argv[2]) if len(argv) > 2 else (640, 480)
    rclpy.init()
    node = Node("fleetctl_sim_camera")
    SimCamera(node, topic, rate_hz, width, height)
    executor: Any = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        try_shutdown()


def _size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` as two positive ints (SystemExit naming the argument otherwise)."""
    width, sep, height = text.lower().partition("x")
    if not (sep and width.isdigit() and height.isdigit() and int(width) > 0 < int(height)):
        raise SystemExit(f"simcamera: size {text!r} is not WIDTHxHEIGHT (e.g. 320x240)")
    return int(width), int(height)


if __name__ == "__main__":
    main(sys.argv[1:])
