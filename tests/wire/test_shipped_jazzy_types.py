"""Jazzy message types that rosbags' type store lacks are shipped with fleetctl.

``nav_msgs/msg/Goals`` (new in Jazzy's nav_msgs 5.3) was known to a robot's client (from
its installed packages) but not to the relay: the Foxglove listener offered no channel
for it (``no ros2msg schema for nav_msgs/msg/Goals: Type 'nav_msgs/msg/Goals' is
unknown``) and the page had no layout for it.
"""

from __future__ import annotations

from fleetctl.wire.codec import Codec
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.ros2msg import type_hash

# What Jazzy's nav_msgs advertises (share/nav_msgs/msg/Goals.json of ros-jazzy-nav-msgs).
GOALS_HASH = "RIHS01_02305a51633b5c04d8979b878a7577cafd422f8a07465c878b17a920af3759e9"


def test_goals_is_a_default_type_with_jazzys_hash() -> None:
    registry = TypeRegistry.default()
    assert registry.get("nav_msgs/msg/Goals").name == "nav_msgs/msg/Goals"
    assert type_hash(registry, "nav_msgs/msg/Goals") == GOALS_HASH


def test_goals_round_trips_cdr_and_flatbuffers() -> None:
    codec = Codec(TypeRegistry.default())
    store = codec.registry.typestore
    types = store.types
    pose = types["geometry_msgs/msg/PoseStamped"](
        types["std_msgs/msg/Header"](types["builtin_interfaces/msg/Time"](3, 4), "map"),
        types["geometry_msgs/msg/Pose"](types["geometry_msgs/msg/Point"](1.0, 2.0, 0.0),
                                        types["geometry_msgs/msg/Quaternion"](0, 0, 0, 1)))
    goals = types["nav_msgs/msg/Goals"](
        types["std_msgs/msg/Header"](types["builtin_interfaces/msg/Time"](3, 4), "map"),
        [pose, pose])
    cdr = store.serialize_cdr(goals, "nav_msgs/msg/Goals")
    frame = codec.encode(store.deserialize_cdr(cdr, "nav_msgs/msg/Goals"),
                         "nav_msgs/msg/Goals", "/r1/goals")
    meta, back = codec.decode(frame)
    assert meta.type == "nav_msgs/msg/Goals"
    assert [g.pose.position.y for g in back.goals] == [2.0, 2.0]
