"""The default topic set of a mobile robot's client config (docs/design.md section 7)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PublishTopic:
    """A local topic the robot client sends to the fleet (``publish:`` in client.yaml).

    Attributes:
        topic: the local ROS topic; it goes out as ``/<robot><topic>``.
        type: ROS 2 type name.
        priority: weight in the client's fair-priority queue (higher goes first).
        rate_limit_hz: at most this many messages per second; ``None``: no limit.
        no_drop: reliable, in-order delivery (never replaced by a newer message).
    """

    topic: str
    type: str
    priority: float
    rate_limit_hz: float | None
    no_drop: bool = False


# Why these numbers: localization and odometry are small and what an operator watches most,
# so they go first and fast; scans next; camera and point clouds are big and only useful
# fresh, so they are rate-limited hardest and yield to everything else. /events is the
# robot's log of discrete happenings, which must all arrive (no_drop). /status is sent by
# the client itself and is not listed here.
DEFAULT_PUBLISH: tuple[PublishTopic, ...] = (
    PublishTopic("/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", 5.0, 10.0),
    PublishTopic("/odom", "nav_msgs/msg/Odometry", 4.0, 10.0),
    PublishTopic("/scan", "sensor_msgs/msg/LaserScan", 3.0, 10.0),
    PublishTopic("/camera/image/compressed", "sensor_msgs/msg/CompressedImage", 1.0, 5.0),
    PublishTopic("/points", "sensor_msgs/msg/PointCloud2", 0.5, 2.0),
    PublishTopic("/events", "std_msgs/msg/String", 10.0, None, no_drop=True),
)
