"""The messages behind the golden byte fixtures in ``tests/wire/fixtures/``.

Regenerate the fixtures (only when the wire format changes on purpose, and say so in the
change) with::

    .venv/bin/python -m tests.wire.golden

The test then compares our encoder's bytes with the stored ones, and decodes them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.samples import header

FIXTURES = Path(__file__).with_name("fixtures")


def golden_cases(codec: Codec) -> dict[str, tuple[str, str, Any, dict[str, Any]]]:
    """``{fixture file stem: (type, topic, message, encode keyword arguments)}``."""
    registry = codec.registry
    cls = {name: registry.get(name).cls for name in (
        "amrl_msgs/msg/RobofleetStatus", "amrl_msgs/msg/RobofleetSubscription",
        "sensor_msgs/msg/LaserScan", "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/Pose",
        "geometry_msgs/msg/Point", "geometry_msgs/msg/Quaternion", "std_msgs/msg/String")}
    hdr = header(registry, "map", stamp_ns=1_700_000_000_500_000_000)
    pose = cls["geometry_msgs/msg/Pose"](cls["geometry_msgs/msg/Point"](1.5, -2.25, 0.0),
                                         cls["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.5, 1.0))
    scan = cls["sensor_msgs/msg/LaserScan"](
        header(registry, "laser", stamp_ns=1_700_000_000_000_000_001), -1.0, 1.0, 0.25, 0.0,
        0.1, 0.05, 30.0, np.array([1, 2, 3, 4, 5, 6, 7, 8, 9], dtype=np.float32),
        np.array([], dtype=np.float32))
    return {
        "robofleet_status": ("amrl_msgs/msg/RobofleetStatus", "/husky1/status",
                             cls["amrl_msgs/msg/RobofleetStatus"]("ok", True, 0.75, "dock"),
                             {"publish_time_ns": 1_700_000_000_000_000_000, "seq": 12}),
        "robofleet_subscription": ("amrl_msgs/msg/RobofleetSubscription", "/subscriptions",
                                   cls["amrl_msgs/msg/RobofleetSubscription"]("/husky1/.*", 1),
                                   {}),
        "laser_scan_small": ("sensor_msgs/msg/LaserScan", "/husky1/scan", scan, {"seq": 3}),
        "pose_stamped": ("geometry_msgs/msg/PoseStamped", "/husky1/goal_pose",
                         cls["geometry_msgs/msg/PoseStamped"](hdr, pose),
                         {"no_drop": True, "seq": 1}),
        # MsgMetadata's trailing latched field (vtable slot 5), issue 18.
        "robot_description_latched": ("std_msgs/msg/String", "/husky1/robot_description",
                                      cls["std_msgs/msg/String"]("<robot name='husky'/>"),
                                      {"seq": 2, "publish_time_ns": 1_700_000_000_000_000_000,
                                       "latched": True}),
    }


def main() -> None:
    """Write the fixtures."""
    codec = default_codec()
    FIXTURES.mkdir(exist_ok=True)
    for stem, (type_name, topic, msg, kwargs) in golden_cases(codec).items():
        frame = codec.encode(msg, type_name, topic, **kwargs)
        FIXTURES.joinpath(f"{stem}.bin").write_bytes(frame)
        print(f"{stem}.bin: {len(frame)} bytes")


if __name__ == "__main__":
    main()
