"""client.yaml loading: defaults, resolution, and one clear error per bad field."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from fleetctl.client.config import (
    ClientLimits,
    StatusSpec,
    load_client_config,
    parse_client_config,
)
from fleetctl.errors import ConfigError, ExitCode

DESIGN_EXAMPLE = """\
server_url: ws://10.8.0.1:8080/
robot_name: husky1
bind_address: null
token_file: null
publish:
  - topic: /scan
    type: sensor_msgs/msg/LaserScan
    priority: 1.0
    rate_limit_hz: 10.0
    no_drop: false
    remote_topic: null
subscribe:
  - remote_topic: /husky1/goal_pose
    type: geometry_msgs/msg/PoseStamped
    local_topic: /goal_pose
status:
  battery_topic: null
  period_s: 1.0
limits:
  max_fragment_bytes: 4194304
  no_drop_queue_messages: 10000
  reconnect_min_s: 0.1
  reconnect_max_s: 5.0
"""


def minimal(**extra: Any) -> dict[str, Any]:
    return {"server_url": "ws://127.0.0.1:8080/", "robot_name": "r1", **extra}


def test_design_example_loads(tmp_path: Path) -> None:
    path = tmp_path / "client.yaml"
    path.write_text(DESIGN_EXAMPLE)
    cfg = load_client_config(path)
    assert cfg.robot_name == "husky1" and cfg.token is None and cfg.bind_address is None
    (scan,) = cfg.publish
    assert scan.remote_topic == "/husky1/scan" and scan.rate_limit_hz == 10.0
    (goal,) = cfg.subscribe
    assert goal.local_topic == "/goal_pose" and not goal.is_regex
    assert cfg.status == StatusSpec() and cfg.limits == ClientLimits()
    assert cfg.status_topic == "/husky1/status"


def test_defaults_and_type_normalization() -> None:
    cfg = parse_client_config(minimal(
        publish=[{"topic": "/events", "type": "std_msgs/String", "no_drop": True,
                  "remote_topic": "/fleet/events"}],
        subscribe=[{"remote_topic": "/r[0-9]+/cmd", "type": "RobofleetStatus"},
                   {"remote_topic": "/r1/goal", "type": "geometry_msgs/msg/PoseStamped"}]))
    (events,) = cfg.publish
    assert events.type == "std_msgs/msg/String" and events.priority == 1.0
    assert events.remote_topic == "/fleet/events" and events.rate_limit_hz is None
    regex, plain = cfg.subscribe
    assert regex.is_regex and regex.local_topic is None
    assert regex.type == "amrl_msgs/msg/RobofleetStatus"
    assert plain.local_topic == "/r1/goal"
    assert isinstance(cfg.publish, tuple)


def test_compression_defaults_to_none_and_accepts_the_codecs(tmp_path: Path) -> None:
    path = tmp_path / "client.yaml"
    path.write_text(DESIGN_EXAMPLE.replace("    remote_topic: null\n", "    remote_topic: null\n"
                                           "    compression: zstd\n"
                                           "  - topic: /map\n"
                                           "    type: nav_msgs/msg/OccupancyGrid\n"
                                           "    compression: deflate\n"
                                           "  - topic: /odom\n"
                                           "    type: nav_msgs/msg/Odometry\n"
                                           "  - topic: /plan\n"
                                           "    type: nav_msgs/msg/Path\n"
                                           "    compression: null\n"))
    cfg = load_client_config(path)
    assert [p.compression for p in cfg.publish] == ["zstd", "deflate", "none", "none"]
    # The status topic may be published by an entry, uncompressed.
    status = parse_client_config(minimal(publish=[
        {"topic": "/status", "type": "amrl_msgs/msg/RobofleetStatus", "compression": "none"}]))
    assert status.publish[0].remote_topic == status.status_topic


def test_token_file_is_read_relative_and_never_shown(tmp_path: Path) -> None:
    (tmp_path / "secret").write_text("s3cret-token\n")
    (tmp_path / "client.yaml").write_text(
        "server_url: wss://fleet:8443/\nrobot_name: r1\ntoken_file: secret\n")
    cfg = load_client_config(tmp_path / "client.yaml")
    assert cfg.token == "s3cret-token"
    assert "s3cret" not in repr(cfg)


@pytest.mark.parametrize(("data", "expected"), [
    (minimal(server_url="http://x/"), "client.yaml: server_url: must be ws://"),
    (minimal(robot_name="1bad"), "robot_name: must match"),
    ({"robot_name": "r1"}, "server_url: is required"),
    (minimal(extra=1), "extra: unknown field"),
    (minimal(bind_address="not-an-ip"), "bind_address: not an IP address"),
    (minimal(publish={"topic": "/a"}), "publish: must be a list"),
    (minimal(publish=[{"topic": "scan", "type": "std_msgs/msg/String"}]),
     "publish[0] (scan): topic: not a ROS topic name"),
    (minimal(publish=[{"topic": "/a", "type": "std_msgs/msg/Nope"}]),
     "publish[0] (/a): type: unknown message type"),
    (minimal(publish=[{"topic": "/a", "type": "not a type"}]),
     "publish[0] (/a): type: not a ROS type name"),
    (minimal(publish=[{"topic": "/a"}]), "publish[0] (/a): type: is required"),
    (minimal(publish=[{"topic": "/a", "type": "std_msgs/msg/String", "priority": -1}]),
     "publish[0] (/a): priority: must be >= 0"),
    (minimal(publish=[{"topic": "/a", "type": "std_msgs/msg/String", "rate_limit_hz": 0}]),
     "rate_limit_hz: must be > 0 or null, got 0"),
    (minimal(publish=[{"topic": "/a", "type": "std_msgs/msg/String", "no_drop": "yes"}]),
     "no_drop: must be true or false"),
    (minimal(publish=[{"topic": "/a", "type": "std_msgs/msg/String", "speed": 1}]),
     "publish[0] (/a): speed: unknown field"),
    (minimal(publish=[{"topic": "/a", "type": "std_msgs/msg/String"},
                      {"topic": "/b", "type": "std_msgs/msg/String", "remote_topic": "/r1/a"}]),
     "publish[1] (/b): remote_topic: /r1/a is already sent by publish[0]"),
    (minimal(publish=["/a"]), "publish[0]: entry: must be a mapping"),
    (minimal(publish=[{"topic": "/a", "type": "std_msgs/msg/String", "compression": "gzip"}]),
     "publish[0] (/a): compression: must be one of none, zstd, deflate, got 'gzip'"),
    (minimal(publish=[{"topic": "/a", "type": "std_msgs/msg/String", "compression": True}]),
     "publish[0] (/a): compression: must be one of"),
    (minimal(publish=[{"topic": "/status", "type": "amrl_msgs/msg/RobofleetStatus",
                       "compression": "zstd"}]),
     "publish[0] (/status): compression: must be none on the status topic"),
    (minimal(publish=[{"topic": "/s", "type": "amrl_msgs/msg/RobofleetStatus",
                       "remote_topic": "/r1/status", "compression": "deflate"}]),
     "publish[0] (/s): compression: must be none on the status topic"),
    (minimal(subscribe=[{"remote_topic": "/a/(", "type": "std_msgs/msg/String"}]),
     "subscribe[0] (/a/(): remote_topic: neither a topic nor a valid RE2 regex"),
    (minimal(subscribe=[{"remote_topic": "/a", "type": "std_msgs/msg/String",
                         "local_topic": "x"}]), "subscribe[0] (/a): local_topic: not a ROS"),
    (minimal(status={"period_s": 0}), "status: period_s: must be > 0"),
    (minimal(status={"battery_topic": 5}), "status: battery_topic: must be a non-empty"),
    (minimal(limits={"max_fragment_bytes": 100}),
     "limits: max_fragment_bytes: must be between 512"),
    (minimal(limits={"max_fragment_bytes": 1.5}), "max_fragment_bytes: must be an integer"),
    (minimal(limits={"reconnect_min_s": 2.0, "reconnect_max_s": 1.0}),
     "limits: reconnect_max_s: must be >= reconnect_min_s"),
    (minimal(limits={"reconnect_min_s": float("nan")}), "reconnect_min_s: must be > 0"),
    (minimal(limits={"scheduler": "fifo"}),
     "limits: scheduler: must be one of adaptive, robofleet, got 'fifo'"),
    ([1, 2], "document: must be a mapping"),
])
def test_bad_field_names_file_entry_and_field(data: Any, expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_client_config(data, source="client.yaml")
    assert expected in str(info.value)
    assert str(info.value).startswith("client.yaml: ")
    assert info.value.exit_code == ExitCode.CONFIG


def test_robofleet_scheduler_sends_whole_frames_one_in_flight() -> None:
    from fleetctl.client.transport import scheduler_config_for

    adaptive = scheduler_config_for(parse_client_config(minimal(), source="c.yaml"))
    assert adaptive.fragments and adaptive.fixed_window_messages is None
    cfg = parse_client_config(minimal(limits={"scheduler": "robofleet"}), source="c.yaml")
    assert cfg.limits.scheduler == "robofleet"
    robofleet = scheduler_config_for(cfg)
    assert not robofleet.fragments and robofleet.fixed_window_messages == 1


def test_file_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_client_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("server_url: [unclosed\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: not valid YAML"):
        load_client_config(bad)
    (tmp_path / "c.yaml").write_text("server_url: ws://h/\nrobot_name: r\ntoken_file: nope\n")
    with pytest.raises(ConfigError, match="token_file: cannot read"):
        load_client_config(tmp_path / "c.yaml")
    (tmp_path / "empty").write_text("\n")
    (tmp_path / "d.yaml").write_text("server_url: ws://h/\nrobot_name: r\ntoken_file: empty\n")
    with pytest.raises(ConfigError, match=r"token_file: .* must hold one token"):
        load_client_config(tmp_path / "d.yaml")
