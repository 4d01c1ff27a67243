"""server.yaml's msg_types (the fleet's own message types): what is accepted, and a
config error naming the file and the field for everything else."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from fleetctl.errors import ConfigError
from fleetctl.server.config import parse_server_config
from fleetctl.server.msgtypes import MAX_DEFINITION_BYTES, codec_for

PATH = Path("/srv/server.yaml")
STATUS = {"type": "my_robot_msgs/msg/Status", "definition": "uint8 mode\nBattery battery\n"}
BATTERY = {"type": "my_robot_msgs/msg/Battery", "definition": "float32 voltage_v\n"}


def _config(msg_types: Any) -> Any:
    return parse_server_config({"auth_map": "auth.yaml", "msg_types": msg_types}, PATH)


def test_definitions_are_kept_and_give_one_codec_per_set() -> None:
    config = _config([STATUS, BATTERY])
    assert config.msg_types == (("my_robot_msgs/msg/Status", STATUS["definition"]),
                                ("my_robot_msgs/msg/Battery", BATTERY["definition"]))
    codec = codec_for(config.msg_types)
    assert codec is codec_for(_config([STATUS, BATTERY]).msg_types)
    assert "my_robot_msgs/msg/Status" in codec.registry
    assert _config(None).msg_types == ()
    assert "my_robot_msgs/msg/Status" not in codec_for(()).registry


@pytest.mark.parametrize(("msg_types", "expected"), [
    ({"type": "a/msg/B"}, "field 'msg_types' must be a list of at most 1000"),
    ([STATUS], "field 'msg_types': my_robot_msgs/msg/Status.battery: unknown message type "
               "my_robot_msgs/msg/Battery"),
    ([{"type": "my_msgs/msg/A", "definition": "int32[ x\n"}],
     "field 'msg_types': cannot parse the .msg text of my_msgs/msg/A: Could not parse:"),
    ([{"type": "std_msgs/msg/String", "definition": "string data\n"}],
     "field 'msg_types': std_msgs/msg/String is a ROS 2 Jazzy or fleetctl type already"),
    ([BATTERY, BATTERY], "field 'msg_types': my_robot_msgs/msg/Battery is defined twice"),
    ([{"type": "my_msgs/Battery", "definition": "int32 x\n"}],
     "field 'msg_types[0].type' must be a pkg/msg/Name type name"),
    ([{"type": "../msg/Battery", "definition": "int32 x\n"}],
     "field 'msg_types[0].type' must be a pkg/msg/Name type name"),
    ([{"type": "my_msgs/msg/A", "definition": "#" * (MAX_DEFINITION_BYTES + 1)}],
     f"field 'msg_types[0].definition' must be the .msg text, at most {MAX_DEFINITION_BYTES}"),
    ([{"type": "my_msgs/msg/A"}], "field 'msg_types[0]' must be a mapping of type and "),
    ([{"type": "my_msgs/msg/A", "definition": "int32 x\n", "x": 1}],
     "unknown field 'msg_types[0].x'"),
    (["my_msgs/msg/A"], "field 'msg_types[0]' must be a mapping"),
])
def test_bad_msg_types_are_config_errors(msg_types: Any, expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        _config(msg_types)
    assert str(info.value).startswith(f"{PATH}: {expected}"), str(info.value)
    assert "\n" not in str(info.value)
