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
    (minimal(publish=[{"topic": "/a", "type": "std_msgs/msg/String", "priority": 10**400}]),
     "publish[0] (/a): priority: must be a finite number, got 1000"),  # was OverflowError
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
    (minimal(subscribe=[{"remote_topic": "\ud800[", "type": "std_msgs/msg/String"}]),
     "remote_topic: neither a topic nor a valid RE2 regex: not UTF-8 text"),
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
    (minimal(limits={"outage_dial_interval_s": 0.001}),
     "limits: outage_dial_interval_s: must be between 0.005 and 0.25, got 0.001"),
    (minimal(limits={"outage_dial_interval_s": "fast"}),
     "limits: outage_dial_interval_s: must be a number, got 'fast'"),
    (minimal(limits={"standby_connection": "yes"}),
     "limits: standby_connection: must be true or false, got 'yes'"),
    (minimal(limits={"dial_ahead_of_messages": 1}),
     "limits: dial_ahead_of_messages: must be true or false, got 1"),
    (minimal(limits={"deflate_on_slow_links": "no"}),
     "limits: deflate_on_slow_links: must be true or false, got 'no'"),
    ([1, 2], "document: must be a mapping"),
    (None, "client.yaml: the file is empty (a client config needs at least server_url and "
           "robot_name)"),  # was "document: must be a mapping, got NoneType"
    ({**minimal(), "publsh": []}, "publsh: unknown field (did you mean publish? allowed: "),
    (minimal(publish=[{"topic": "/a", "typ": "std_msgs/msg/String"}]),
     "publish[0] (/a): typ: unknown field (did you mean type? allowed: "),
    (minimal(tf={}, subscribe=[{"remote_topic": "/husky1/tf_static", "local_topic": "/tf_static",
                                "type": "tf2_msgs/msg/TFMessage"}]),
     "client.yaml: subscribe[0] (/husky1/tf_static): local_topic: /tf_static is read by the tf "
     "section, which would send what arrives there as r1's own TF; republish it under a topic "
     "of its own (e.g. /tf_static_husky1)"),  # docs said refused; it was accepted
    (minimal(tf={}, subscribe=[{"remote_topic": "/.*/tf", "local_topic": "/tf",
                                "type": "tf2_msgs/msg/TFMessage"}]),
     "subscribe[0] (/.*/tf): local_topic: /tf is read by the tf section"),
    (minimal(publish=[{"topic": "/chatter", "type": "std_msgs/msg/String"}],
             subscribe=[{"remote_topic": "/r1/chatter", "local_topic": "/chatter",
                         "type": "std_msgs/msg/String"}]),
     "client.yaml: subscribe[0] (/r1/chatter): local_topic: /chatter is publish[0]'s topic, "
     "sent as /r1/chatter, which this entry receives: every message would loop back to the "
     "fleet; give it another local_topic"),
    (minimal(publish=[{"topic": "/a", "type": "std_msgs/msg/String"},
                      {"topic": "/chatter", "type": "std_msgs/msg/String"}],
             subscribe=[{"remote_topic": "/r1/.*", "local_topic": "/chatter",
                         "type": "std_msgs/msg/String"}]),
     "subscribe[0] (/r1/.*): local_topic: /chatter is publish[1]'s topic"),
    (minimal(tf=True), "client.yaml: tf: must be a mapping, got true (tf: {} turns TF on "
                       "with the defaults; leave it out for no TF)"),
    (minimal(status={"location": "a\nb"}),
     "status: location: must be one line of at most 200 printable characters, got 'a\\nb'"),
    (minimal(status={"location": "x" * 201}), "status: location: must be one line"),
    (minimal(status={"location": 3}), "status: location: "),
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


def test_the_outage_dial_interval_reaches_the_link_s_dial_pace() -> None:
    from fleetctl.client.linktuning import LinkTuning
    from fleetctl.client.transport import RobotLink

    default = parse_client_config(minimal(), source="c.yaml")
    assert default.limits.outage_dial_interval_s == 0.01
    flat = RobotLink(default, on_frame=lambda f: None, tuning=LinkTuning()).tuning.dial
    assert flat.stagger_at(0.0) == flat.stagger_at(59.0) == 0.01  # 10 ms for a minute
    cfg = parse_client_config(minimal(limits={"outage_dial_interval_s": 0.04}),
                              source="c.yaml")
    link = RobotLink(cfg, on_frame=lambda f: None, tuning=LinkTuning())
    assert link.tuning.dial.outage_stagger_s == 0.04
    assert link.tuning.dial.stagger_at(0.0) == 0.01  # doubling from 10 ms ...
    assert link.tuning.dial.stagger_at(30.0) == 0.04  # ... to it, held to a minute
    assert link.tuning.dial.stagger_at(90.0) == link.tuning.dial.stagger_s


def test_the_standby_connection_is_on_unless_turned_off() -> None:
    from fleetctl.client.linktuning import LinkTuning
    from fleetctl.client.transport import RobotLink

    default = parse_client_config(minimal(), source="c.yaml")
    assert default.limits.standby_connection
    assert RobotLink(default, on_frame=lambda f: None,
                     tuning=LinkTuning()).stats()["standby"]["open"] is False
    off = parse_client_config(minimal(limits={"standby_connection": False}), source="c.yaml")
    assert not off.limits.standby_connection
    assert RobotLink(off, on_frame=lambda f: None, tuning=LinkTuning()).stats()["standby"] is None


def test_dialing_ahead_of_messages_is_on_unless_turned_off() -> None:
    assert parse_client_config(minimal(), source="c.yaml").limits.dial_ahead_of_messages
    off = parse_client_config(minimal(limits={"dial_ahead_of_messages": False}),
                              source="c.yaml")
    assert not off.limits.dial_ahead_of_messages


def test_deflate_on_slow_links_is_on_unless_turned_off() -> None:
    """Off, the robot never deflates fragments of large messages, whatever the link
    (fleetctl.client.slowdeflate: a threshold of 0 never turns it on)."""
    from fleetctl.client.linktuning import LinkTuning
    from fleetctl.client.transport import RobotLink

    on = parse_client_config(minimal(), source="c.yaml")
    assert on.limits.deflate_on_slow_links
    off = parse_client_config(minimal(limits={"deflate_on_slow_links": False}),
                              source="c.yaml")
    link = RobotLink(off, on_frame=lambda f: None, tuning=LinkTuning())
    assert link._slow_deflate.settings.on_below_Bps == 0.0
    assert not link._slow_deflate.decide(1.0, 0.0)  # 8 bit/s on the wire: still off
    assert not link._slow_deflate.decide(1.0, 60.0)
    rule = RobotLink(on, on_frame=lambda f: None, tuning=LinkTuning())._slow_deflate
    assert not rule.decide(1.0, 0.0)  # on once it stays that slow for on_after_s
    assert rule.decide(1.0, rule.settings.on_after_s)


def test_file_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_client_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("server_url: [unclosed\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml:2: not valid YAML"):
        load_client_config(bad)
    (tmp_path / "c.yaml").write_text("server_url: ws://h/\nrobot_name: r\ntoken_file: nope\n")
    with pytest.raises(ConfigError, match="token_file: cannot read"):
        load_client_config(tmp_path / "c.yaml")
    (tmp_path / "n.yaml").write_text('server_url: ws://h/\nrobot_name: r\ntoken_file: "a\\0"\n')
    with pytest.raises(ConfigError, match=r"token_file: cannot read .*: the path contains a NUL"):
        load_client_config(tmp_path / "n.yaml")  # was ValueError from os.open
    (tmp_path / "empty").write_text("\n")
    (tmp_path / "d.yaml").write_text("server_url: ws://h/\nrobot_name: r\ntoken_file: empty\n")
    with pytest.raises(ConfigError, match=r"token_file: .* must hold one token"):
        load_client_config(tmp_path / "d.yaml")
    (tmp_path / "zero").symlink_to("/dev/zero")
    (tmp_path / "z.yaml").write_text("server_url: ws://h/\nrobot_name: r\ntoken_file: zero\n")
    with pytest.raises(ConfigError, match=r"token_file: cannot read .*zero: not a regular file"):
        load_client_config(tmp_path / "z.yaml")
    (tmp_path / "y.yaml").symlink_to("/dev/zero")
    with pytest.raises(ConfigError, match=r"y\.yaml: cannot read .*: not a regular file"):
        load_client_config(tmp_path / "y.yaml")


def _cam(**video: Any) -> dict[str, Any]:
    return {"topic": "/cam", "type": "sensor_msgs/msg/Image", "video": video}


def _cloud(**viewer: Any) -> dict[str, Any]:
    return {"topic": "/pts", "type": "sensor_msgs/msg/PointCloud2", "viewer_cloud": viewer}


def test_video_viewer_cloud_and_tf_defaults() -> None:
    from fleetctl.client.config import TfSpec, VideoSpec, ViewerCloudSpec

    cfg = parse_client_config(minimal(
        publish=[_cam(), _cloud(), {"topic": "/c", "type": "sensor_msgs/CompressedImage",
                                    "video": {"codec": "av1", "keyframe_interval_s": 1}}],
        tf={}), source="c.yaml")
    assert cfg.publish[0].video == VideoSpec("h264", 1000, 100, 2.0)
    assert cfg.publish[0].viewer_cloud is None and cfg.publish[1].video is None
    assert cfg.publish[1].viewer_cloud == ViewerCloudSpec(resolution_m=0.01)
    assert cfg.publish[2].video == VideoSpec(codec="av1", keyframe_interval_s=1.0)
    assert cfg.tf == TfSpec(0.01, 0.01, 10.0)
    plain = parse_client_config(minimal(tf=None), source="c.yaml")
    assert plain.tf is None


@pytest.mark.parametrize(("data", "expected"), [
    (minimal(publish=[_cam(codec="mjpeg")]),
     "publish[0] (/cam): video: codec: must be one of h264, vp8, vp9, av1, got 'mjpeg'"),
    (minimal(publish=[_cam(max_bitrate_kbps=0)]),
     "publish[0] (/cam): video: max_bitrate_kbps: must be between 1"),
    (minimal(publish=[_cam(max_bitrate_kbps=500.5)]),
     "video: max_bitrate_kbps: must be an integer"),
    (minimal(publish=[_cam(min_bitrate_kbps=-5)]), "video: min_bitrate_kbps: must be between 1"),
    (minimal(publish=[_cam(max_bitrate_kbps=200, min_bitrate_kbps=300)]),
     "publish[0] (/cam): video: min_bitrate_kbps: must be <= max_bitrate_kbps (200), got 300"),
    (minimal(publish=[_cam(keyframe_interval_s=0)]), "video: keyframe_interval_s: must be > 0"),
    (minimal(publish=[_cam(fps=30)]), "publish[0] (/cam): video: fps: unknown field"),
    (minimal(publish=[{"topic": "/cam", "type": "sensor_msgs/msg/Image", "video": "h264"}]),
     "publish[0] (/cam): video: must be a mapping"),
    (minimal(publish=[{"topic": "/d", "type": "stereo_msgs/msg/DisparityImage",
                       "video": {}}]),
     "publish[0] (/d): video: only for sensor_msgs/msg/Image or "
     "sensor_msgs/msg/CompressedImage, not stereo_msgs/msg/DisparityImage"),
    (minimal(publish=[_cloud(resolution_m=0)]),
     "publish[0] (/pts): viewer_cloud: resolution_m: must be between 0.001 and 1, got 0"),
    (minimal(publish=[_cloud(resolution_m=2)]), "resolution_m: must be between 0.001 and 1"),
    (minimal(publish=[_cloud(voxel=1)]), "publish[0] (/pts): viewer_cloud: voxel: unknown"),
    (minimal(publish=[{"topic": "/s", "type": "sensor_msgs/msg/LaserScan",
                       "viewer_cloud": {}}]),
     "publish[0] (/s): viewer_cloud: only for sensor_msgs/msg/PointCloud2"),
    (minimal(publish=[_cloud(), {"topic": "/pts/viewer", "type": "std_msgs/msg/String"}]),
     "publish[1] (/pts/viewer): remote_topic: /r1/pts/viewer is already sent by publish[0]"),
    (minimal(tf={"translation_delta_m": -1}), "tf: translation_delta_m: must be >= 0"),
    (minimal(tf={"rotation_delta_rad": 4}), "tf: rotation_delta_rad: must be between 0 and pi"),
    (minimal(tf={"max_rate_hz": 0}), "tf: max_rate_hz: must be > 0 and <= 1000, got 0"),
    (minimal(tf={"rate": 1}), "tf: rate: unknown field"),
    (minimal(tf=[1]), "tf: entry: must be a mapping"),
    (minimal(tf={}, publish=[{"topic": "/tf", "type": "tf2_msgs/msg/TFMessage"}]),
     "publish[0] (/tf): remote_topic: /r1/tf is sent by the tf section"),
    (minimal(tf={}, publish=[{"topic": "/x", "type": "tf2_msgs/msg/TFMessage",
                              "remote_topic": "/r1/tf_static"}]),
     "publish[0] (/x): remote_topic: /r1/tf_static is sent by the tf section"),
])
def test_media_fields_name_entry_and_field(data: Any, expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_client_config(data, source="client.yaml")
    assert expected in str(info.value)


def test_a_bad_subscribe_regex_is_one_error_line_and_no_re2_log(
        tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("server_url: ws://h/\nrobot_name: r\nsubscribe:\n"
                    "  - remote_topic: '/a/(('\n    type: std_msgs/msg/String\n"
                    "    local_topic: /x\n")
    with pytest.raises(ConfigError, match="neither a topic nor a valid RE2 regex"):
        load_client_config(path)
    assert "((" not in capfd.readouterr().err


def test_status_location_is_read() -> None:
    """The page's robot list has a Location column that no fleetctl robot could fill."""
    cfg = parse_client_config(minimal(status={"location": "warehouse A, aisle 3"}),
                              source="client.yaml")
    assert cfg.status.location == "warehouse A, aisle 3"
    assert parse_client_config(minimal(), source="client.yaml").status.location == ""


def _workspace(root: Path, msgs: dict[str, str]) -> Path:
    """An install prefix as colcon makes one: ``share/<pkg>/msg/<Name>.msg`` per type."""
    for name, text in msgs.items():
        package, _, short = name.partition("/msg/")
        (root / "share" / package / "msg").mkdir(parents=True, exist_ok=True)
        (root / "share" / package / "msg" / f"{short}.msg").write_text(text)
    return root


def test_types_of_the_robots_own_packages_are_accepted(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A robot's own message package (sourced workspace on AMENT_PREFIX_PATH) is carried by
    the client's run-time registry; the config check refused it as 'not in the type
    registry' before the client started."""
    from fleetctl.wire.registry import TypeRegistry

    ws = _workspace(tmp_path / "install", {
        "my_robot_msgs/msg/Status": "std_msgs/Header header\nfloat32 motor_temp\n"
                                    "my_robot_msgs/Mode mode\n",
        "my_robot_msgs/msg/Mode": "uint8 AUTO=1\nuint8 value\n"})
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(ws))
    config = parse_client_config(minimal(
        publish=[{"topic": "/robot_status", "type": "my_robot_msgs/Status"}],
        subscribe=[{"remote_topic": "/r2/robot_status", "type": "my_robot_msgs/msg/Status"}]))
    assert config.publish[0].type == config.subscribe[0].type == "my_robot_msgs/msg/Status"
    # ... the type the client's registry (runner.build_registry) then encodes.
    registry = TypeRegistry.default()
    registry.from_rclpy()
    assert "my_robot_msgs/msg/Status" in registry

    # A typo is named with the installed type it most likely meant, and where it looked.
    with pytest.raises(ConfigError) as typo:
        parse_client_config(minimal(publish=[{"topic": "/s", "type": "my_robot_msgs/msg/Statu"}]))
    said = str(typo.value)
    assert "publish[0] (/s): type: unknown message type 'my_robot_msgs/msg/Statu'" in said
    assert f"share/my_robot_msgs/msg/Statu.msg under {ws}" in said
    assert "Did you mean my_robot_msgs/msg/Status?" in said

    # Without the workspace sourced: where to look, and what to source.
    monkeypatch.delenv("AMENT_PREFIX_PATH")
    with pytest.raises(ConfigError, match=r"source its workspace's install/setup.bash"):
        parse_client_config(minimal(publish=[{"topic": "/s", "type": "my_robot_msgs/msg/Status"}]))


def test_an_unreadable_package_definition_is_named(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ws = _workspace(tmp_path / "install", {"bad_msgs/msg/Odd": "no_such_pkg/Thing thing\n",
                                           "good_msgs/msg/Fine": "int32 value\n"})
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(ws))
    # Another package's definitions stay usable, as in the client's registry.
    parse_client_config(minimal(publish=[{"topic": "/f", "type": "good_msgs/msg/Fine"}]))
    with pytest.raises(ConfigError) as error:
        parse_client_config(minimal(publish=[{"topic": "/o", "type": "bad_msgs/msg/Odd"}]))
    assert "could not be read" in str(error.value) and "no_such_pkg" in str(error.value)


def test_a_misspelt_standard_type_gets_a_suggestion() -> None:
    with pytest.raises(ConfigError, match=r"Did you mean sensor_msgs/msg/LaserScan\?"):
        parse_client_config(minimal(publish=[{"topic": "/scan",
                                              "type": "sensor_msgs/msg/Laserscan"}]))


@pytest.mark.parametrize("written", [
    b"\xef\xbb\xbfs3cret-token\r\n",  # Notepad / PowerShell 5: a byte order mark, CRLF
    b"s3cret-token\n\n", b"  s3cret-token\t\n"])
def test_the_token_is_what_the_file_holds_without_its_encoding_marks(
        tmp_path: Path, written: bytes) -> None:
    """A byte order mark was sent as the token's first character: 4401 'bad token' for
    a file that showed the right token."""
    (tmp_path / "secret").write_bytes(written)
    cfg = parse_client_config(minimal(token_file="secret"), base_dir=tmp_path)
    assert cfg.token == "s3cret-token"


def test_a_token_the_relay_would_refuse_unseen_is_named_without_echoing_it(
        tmp_path: Path) -> None:
    (tmp_path / "secret").write_text("s3cret-t\u00f6ken\n", encoding="utf-8")
    with pytest.raises(ConfigError) as error:
        parse_client_config(minimal(token_file="secret"), source="c.yaml", base_dir=tmp_path)
    assert str(error.value) == (
        f"c.yaml: token_file: {tmp_path / 'secret'}: a token is printable ASCII of at most "
        "1024 characters: U+00F6 at character 9")
    assert "s3cret" not in str(error.value)
