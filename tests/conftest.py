"""Settings every test shares."""

from __future__ import annotations

import os

# ROS 2 discovery stays on loopback for every rclpy node a test starts, in this process or
# in a child: the tests must not send multicast onto the machine's network, and on a
# loaded machine multicast discovery over the LAN interface was seen to match too late.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
