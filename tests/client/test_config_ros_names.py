"""Topic names in client.yaml that ROS 2 refuses are config errors, not rcl's traceback."""

from __future__ import annotations

from typing import Any

import pytest

from fleetctl.client.config import MAX_ROS_TOPIC_CHARS, parse_client_config
from fleetctl.errors import ConfigError


def _parse(**entry: Any) -> Any:
    return parse_client_config({"server_url": "ws://127.0.0.1:1/", "robot_name": "r1", **entry},
                               source="client.yaml")


def test_a_private_name_says_to_write_it_in_full() -> None:
    # A driver's ~/state is /NAMESPACE/NODE/state: the client's node would expand ~ to its
    # own name, so it was refused as "not a ROS topic name" without a word on why.
    with pytest.raises(ConfigError) as caught:
        _parse(publish=[{"topic": "~/state", "type": "std_msgs/msg/String"}])
    assert str(caught.value) == (
        "client.yaml: publish[0] (~/state): topic: '~/state' is private to the node that "
        "publishes it (~ is that node's namespace and name); write it in full, e.g. "
        "/NAMESPACE/NODE/state (`ros2 topic list` shows it)")


def test_a_deep_namespace_is_fine_up_to_rmws_limit() -> None:
    deep = "/rg/sensors/front/lidar/scan"
    assert _parse(publish=[{"topic": deep, "type": "sensor_msgs/msg/LaserScan"}]
                  ).publish[0].remote_topic == "/r1" + deep
    longest = "/" + "a" * (MAX_ROS_TOPIC_CHARS - 1)
    assert _parse(publish=[{"topic": longest, "type": "std_msgs/msg/String"}]).publish


@pytest.mark.parametrize(("section", "key"), [("publish", "topic"),
                                              ("subscribe", "local_topic"),
                                              ("subscribe", "remote_topic")])
def test_a_topic_longer_than_ros_allows_is_refused(section: str, key: str) -> None:
    # rcl refuses names over 247 characters: the client stopped at start in rclpy's
    # InvalidTopicNameException (a remote topic without local_topic is the local one).
    name = "/" + "a" * MAX_ROS_TOPIC_CHARS
    entry = {"type": "std_msgs/msg/String", key: name}
    if section == "publish":
        entry["topic"] = name
    elif key == "local_topic":
        entry["remote_topic"] = "/r2/chat"
    with pytest.raises(ConfigError, match=rf"{section}\[0\] .*: {key}: 248 characters, ROS 2 "
                                          r"allows at most 247"):
        _parse(**{section: [entry]})
