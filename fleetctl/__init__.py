"""fleetctl: communication, monitoring and tasking for fleets of ROS 2 robots."""

from __future__ import annotations

__version__ = "0.1.0"
