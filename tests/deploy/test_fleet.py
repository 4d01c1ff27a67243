"""fleet.yaml: round trip, and errors that name the file, the line and the field."""

from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.deploy.fleet import (
    FleetInvalid,
    dump_fleet,
    load_fleet,
    parse_endpoint,
    parse_fleet,
    require_endpoint,
)
from fleetctl.deploy.topics import DEFAULT_PUBLISH
from fleetctl.errors import ConfigError

GOOD = """\
version: 1
name: campus
endpoint: vpn.example.com:51820
subnet: 10.8.0.0/24
server_ip: 10.8.0.1
robots:
  - name: husky1
    ip: 10.8.0.2
  - name: jackal2
    ip: 10.8.0.3
    extra_receive: ["/husky1/scan"]
users:
  - email: alice@example.com
    role: viewer
    token_sha256: "%s"
""" % ("ab" * 32)


def _error(text: str) -> str:
    with pytest.raises(ConfigError) as info:
        parse_fleet(Path("/f/fleet.yaml"), text)
    return str(info.value)


def test_good_fleet_round_trips() -> None:
    fleet = parse_fleet(Path("fleet.yaml"), GOOD)
    assert [r.name for r in fleet.robots] == ["husky1", "jackal2"]
    assert fleet.robots[1].extra_receive == ("/husky1/scan",)
    again = parse_fleet(Path("fleet.yaml"), dump_fleet(fleet))
    assert again == fleet
    assert dump_fleet(again) == dump_fleet(fleet)


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ("    ip: 10.8.0.3\n", "    ip: 10.8.0.2\n",
         "/f/fleet.yaml:10: robots[1].ip: 10.8.0.2 is already used by robot 'husky1'"),
        ("    ip: 10.8.0.3\n", "    ip: 10.9.0.3\n",
         "/f/fleet.yaml:10: robots[1].ip: 10.9.0.3 is outside the fleet subnet 10.8.0.0/24"),
        ("    ip: 10.8.0.3\n", "    ip: 10.8.0.1\n",
         "/f/fleet.yaml:10: robots[1].ip: 10.8.0.1 is the server's address"),
        ("  - name: jackal2\n", "  - name: husky1\n",
         "/f/fleet.yaml:9: robots[1].name: duplicate robot name 'husky1'"),
        ("  - name: jackal2\n", "  - name: 2jackal\n",
         "/f/fleet.yaml:9: robots[1].name: robot name '2jackal' is not a ROS namespace segment"),
        ("    role: viewer\n", "    role: pilot\n",
         "/f/fleet.yaml:14: users[0].role: unknown role 'pilot'"),
        ("subnet: 10.8.0.0/24\n", "subnet: 10.8.0.1/24\n",
         "/f/fleet.yaml:4: subnet: not a subnet in CIDR form"),
        ("server_ip: 10.8.0.1\n", "server_ip: 10.8.0.1\nservr_port: 1\n",
         "/f/fleet.yaml:6: servr_port: unknown field"),
        ("    extra_receive: [\"/husky1/scan\"]\n", "    extra_receive: [\"(\"]\n",
         "/f/fleet.yaml:11: robots[1].extra_receive[0]: not a valid RE2 regex '('"),
        ("    extra_receive: [\"/husky1/scan\"]\n", "    extra_receive: [\"\\ud800\"]\n",
         "/f/fleet.yaml:11: robots[1].extra_receive[0]: not a valid RE2 regex '\\ud800': "
         "not UTF-8 text"),
        # The relay's own bound on a pattern: a longer one rendered into an auth.yaml the
        # server then refused at start.
        ("    extra_receive: [\"/husky1/scan\"]\n",
         "    extra_receive: [\"/" + "a" * 4096 + "\"]\n",
         "/f/fleet.yaml:11: robots[1].extra_receive[0]: not a valid RE2 regex '/aaaa"),
        ("endpoint: vpn.example.com:51820\n", "endpoint: vpn.example.com\n",
         "/f/fleet.yaml:3: endpoint: expected HOST:PORT"),
        ("version: 1\n", "version: 2\n", "/f/fleet.yaml:1: version: unsupported version 2"),
        ("name: campus\n", "", "/f/fleet.yaml:1: (document): missing required field 'name'"),
        ("    ip: 10.8.0.2\n", "    ip: 10.8.0.2\n    mtu_bytes: big\n",
         "/f/fleet.yaml:9: robots[0].mtu_bytes: expected an integer"),
        # YAML 1.1 reads these as 8080, 8080, 8 and 8080: fleet.yaml's integers are
        # decimal ASCII digits, as the docs say.
        ("server_ip: 10.8.0.1\n", "server_ip: 10.8.0.1\nserver_port: 0x1f90\n",
         "/f/fleet.yaml:6: server_port: expected an integer in decimal ASCII digits without "
         "leading zeros, got '0x1f90'"),
        ("server_ip: 10.8.0.1\n", "server_ip: 10.8.0.1\nserver_port: 8_080\n",
         "/f/fleet.yaml:6: server_port: expected an integer in decimal ASCII digits"),
        ("server_ip: 10.8.0.1\n", "server_ip: 10.8.0.1\nhttps_port: 010\n",
         "/f/fleet.yaml:6: https_port: expected an integer in decimal ASCII digits"),
        ("server_ip: 10.8.0.1\n", "server_ip: 10.8.0.1\nwireguard_port: 2:14:40\n",
         "/f/fleet.yaml:6: wireguard_port: expected an integer in decimal ASCII digits"),
        ("    ip: 10.8.0.2\n", "    ip: 10.8.0.2\n    mtu_bytes: 0b10100000000\n",
         "/f/fleet.yaml:9: robots[0].mtu_bytes: expected an integer in decimal ASCII digits"),
        ("version: 1\n", "version: 0o1\n", "/f/fleet.yaml:1: version: expected an integer"),
        ("endpoint: vpn.example.com:51820\n", "endpoint: vpn.example.com:051820\n",
         "/f/fleet.yaml:3: endpoint: expected HOST:PORT (ASCII, port 1..65535 without a "
         "leading zero), got 'vpn.example.com:051820'"),
        ("  - name: husky1\n", "  - name: [husky1]\n",
         "/f/fleet.yaml:7: robots[0].name: expected a string"),
    ],
)
def test_semantic_errors_name_file_line_field(old: str, new: str, expected: str) -> None:
    assert old in GOOD
    assert _error(GOOD.replace(old, new, 1)).startswith(expected)


@pytest.mark.parametrize(("subnet", "server_ip", "why"), [
    ("0.0.0.0/0", "0.0.0.1", "is too large (at least /8): every robot routes"),
    ("10.0.0.0/7", "10.0.0.1", "is too large (at least /8)"),
    ("0.0.0.0/24", "0.0.0.1", "is in 0.0.0.0/8, not unicast"),
    ("224.0.0.0/24", "224.0.0.1", "is in 224.0.0.0/4, not unicast"),
    ("240.0.0.0/24", "240.0.0.1", "is in 240.0.0.0/4, not unicast"),
])
def test_a_subnet_robots_could_not_route_alone_is_refused(subnet: str, server_ip: str,
                                                          why: str) -> None:
    """0.0.0.0/0 was accepted: every robot's wg0.conf then had AllowedIPs = 0.0.0.0/0 and
    sent all of its traffic (its default route) into the tunnel."""
    text = GOOD.replace("subnet: 10.8.0.0/24", f"subnet: {subnet}").replace(
        "server_ip: 10.8.0.1", f"server_ip: {server_ip}")
    assert _error(text).startswith(f"/f/fleet.yaml:4: subnet: {subnet} {why}")


def test_the_largest_and_the_demo_subnets_are_fine() -> None:
    for subnet, server_ip, robots in (("10.0.0.0/8", "10.0.0.1", ("10.0.0.2", "10.0.0.3")),
                                      ("127.0.1.0/24", "127.0.1.1",
                                       ("127.0.1.2", "127.0.1.3"))):
        text = GOOD.replace("10.8.0.0/24", subnet).replace("10.8.0.1", server_ip).replace(
            "10.8.0.2", robots[0]).replace("10.8.0.3", robots[1])
        assert str(parse_fleet(Path("/f/fleet.yaml"), text).subnet) == subnet


def test_yaml_syntax_error_names_line() -> None:
    message = _error(GOOD.replace("  - name: husky1\n", "  - name: husky1\n bad: [\n"))
    assert message.startswith("/f/fleet.yaml:")
    assert "not valid YAML" in message


def test_an_alias_is_reported_at_its_own_line() -> None:
    """A value written `*name` was reported at its anchor's line (compose gives an alias
    the anchor's node), pointing at the one place that was right."""
    text = GOOD.replace("server_ip: 10.8.0.1\n", "server_ip: 10.8.0.1\nserver_port: &p 80\n")
    text = text.replace("    ip: 10.8.0.3\n", "    ip: 10.8.0.3\n    mtu_bytes: *p\n")
    line = text.splitlines().index("    mtu_bytes: *p") + 1
    assert _error(text) == (f"/f/fleet.yaml:{line}: robots[1].mtu_bytes: must be between "
                            "576 and 9000, got 80")
    # An alias of a collection: the alias's line for the field, the anchor's for what is
    # written inside it; aliases that are fine still read as their anchor's value.
    text = GOOD.replace('    extra_receive: ["/husky1/scan"]\n',
                        '    extra_receive: *rx\n').replace(
        "    ip: 10.8.0.2\n", "    ip: 10.8.0.2\n    extra_send: &rx [5]\n")
    lines = text.splitlines()
    assert _error(text) == (f"/f/fleet.yaml:{lines.index('    extra_send: &rx [5]') + 1}: "
                            "robots[0].extra_send[0]: expected a string")
    fleet = parse_fleet(Path("/f/fleet.yaml"), text.replace("[5]", '["/husky1/x"]'))
    assert fleet.robots[1].extra_receive == fleet.robots[0].extra_send == ("/husky1/x",)


def test_deep_nesting_is_an_error_not_a_recursion_crash() -> None:
    text = "version: 1\nname: x\nrobots: " + "[" * 2000 + "]" * 2000 + "\n"
    assert _error(text) == "/f/fleet.yaml: not valid YAML: nested too deeply"


def test_empty_and_non_mapping() -> None:
    assert _error("") == "/f/fleet.yaml:1: the file is empty"
    assert _error("- 1\n").startswith("/f/fleet.yaml:1: (document): expected a mapping")


def test_missing_directory_and_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        load_fleet(tmp_path / "nope")
    with pytest.raises(ConfigError, match=r"fleet\.yaml: not found"):
        load_fleet(tmp_path)


TOPICS = GOOD.replace("    extra_receive: [\"/husky1/scan\"]\n", """\
    extra_receive: ["/husky1/scan"]
    publish:
      - {topic: /map, type: nav_msgs/msg/OccupancyGrid, rate_limit_hz: 1}
      - {topic: /gps/fix, type: sensor_msgs/msg/NavSatFix}
      - {topic: /scan, type: sensor_msgs/msg/LaserScan, compression: zstd}
    subscribe:
      - {remote_topic: /husky1/map, type: nav_msgs/msg/OccupancyGrid}
    battery_topic: /battery_state
    ros_domain_id: 7
    rmw_implementation: rmw_cyclonedds_cpp
    location: warehouse A
""")


def test_topics_and_ros_fields_round_trip() -> None:
    fleet = parse_fleet(Path("fleet.yaml"), TOPICS)
    jackal = fleet.robots[1]
    assert [p.topic for p in jackal.publish_topics] == ["/map", "/gps/fix", "/scan"]
    assert jackal.publish is not None and jackal.publish[0].rate_limit_hz == 1.0
    assert jackal.publish[1].priority == 1.0 and jackal.publish[2].compression == "zstd"
    assert jackal.battery_topic == "/battery_state"
    assert (jackal.ros_domain_id, jackal.rmw_implementation) == (7, "rmw_cyclonedds_cpp")
    assert (jackal.location, fleet.robots[0].location) == ("warehouse A", "")
    assert fleet.robots[0].publish is None  # the default set, kept as "absent"
    assert len(fleet.robots[0].publish_topics) == len(DEFAULT_PUBLISH)
    again = parse_fleet(Path("fleet.yaml"), dump_fleet(fleet))
    assert again == fleet
    assert "  publish:" not in dump_fleet(fleet).split("- name: jackal2")[0]


def test_endpoint_null_and_absent() -> None:
    for text in (GOOD.replace("vpn.example.com:51820", "null"),
                 GOOD.replace("endpoint: vpn.example.com:51820\n", "")):
        fleet = parse_fleet(Path("fleet.yaml"), text)
        assert fleet.endpoint is None
        assert "endpoint: null" in dump_fleet(fleet)


@pytest.mark.parametrize("endpoint", [
    "[::::]:51820", "[1.2.3]:5", "[fe80::1::2]:1", "a..b:1", "999.1.1.1:1", "1.2.3.4.5:1",
    "a.-b.org:1", "a-.b.org:1", "%s.org:1" % ("a" * 64),
])
def test_endpoint_host_must_be_an_address_or_a_dns_name(endpoint: str) -> None:
    with pytest.raises(FleetInvalid, match="expected HOST:PORT"):
        parse_endpoint(endpoint)
    assert _error(GOOD.replace("vpn.example.com:51820", f"'{endpoint}'")).startswith(
        "/f/fleet.yaml:3: endpoint: expected HOST:PORT")


@pytest.mark.parametrize(("endpoint", "host"), [
    ("[fe80::1]:51820", "[fe80::1]"), ("[::ffff:1.2.3.4]:1", "[::ffff:1.2.3.4]"),
    ("10.0.0.1:51820", "10.0.0.1"), ("vpn-1.example.org:1", "vpn-1.example.org"),
    ("localhost:9", "localhost"), ("1.example:2", "1.example"),
])
def test_endpoint_good_hosts(endpoint: str, host: str) -> None:
    assert parse_endpoint(endpoint)[0] == host


def test_require_endpoint(tmp_path: Path) -> None:
    fleet = parse_fleet(Path("fleet.yaml"), GOOD.replace("vpn.example.com:51820", "null"))
    with pytest.raises(ConfigError) as info:
        require_endpoint(fleet, tmp_path)
    assert str(info.value) == (
        f"{tmp_path / 'fleet.yaml'}: endpoint: not set; run `fleetctl set-endpoint HOST:PORT` "
        "(where robots reach the server's WireGuard)")
    assert require_endpoint(parse_fleet(Path("f"), GOOD), tmp_path) == "vpn.example.com:51820"


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ("/gps/fix, type: sensor_msgs/msg/NavSatFix", "/gps/fix, type: foo_msgs/msg/Bar",
         "/f/fleet.yaml:14: robots[1].publish[1].type: unknown ROS type 'foo_msgs/msg/Bar'"),
        ("/gps/fix, type: sensor_msgs/msg/NavSatFix", "/gps/fix, type: NavSatFix",
         "/f/fleet.yaml:14: robots[1].publish[1].type: 'NavSatFix' is not a ROS type name"),
        ("{topic: /gps/fix,", "{topic: gps/fix,",
         "/f/fleet.yaml:14: robots[1].publish[1].topic: 'gps/fix' is not an absolute ROS topic"),
        ("{topic: /gps/fix,", "{topic: /map,",
         "/f/fleet.yaml:14: robots[1].publish[1].topic: duplicate topic '/map' (also publish[0])"),
        ("{topic: /gps/fix,", "{topic: /status,",
         "/f/fleet.yaml:14: robots[1].publish[1].topic: /status is sent by the client itself"),
        ("rate_limit_hz: 1}", "rate_limit_hz: 0}",
         "/f/fleet.yaml:13: robots[1].publish[0].rate_limit_hz: must be > 0 or null, got 0"),
        ("rate_limit_hz: 1}", "rate_limit_hz: fast}",
         "/f/fleet.yaml:13: robots[1].publish[0].rate_limit_hz: expected a number"),
        ("rate_limit_hz: 1}", "rate_limit_hz: 1, priority: -1}",
         "/f/fleet.yaml:13: robots[1].publish[0].priority: must be >= 0, got -1.0"),
        ("rate_limit_hz: 1}", "rate_limit_hz: .inf}",
         "/f/fleet.yaml:13: robots[1].publish[0].rate_limit_hz: must be a finite number"),
        ("compression: zstd}", "compression: lz4}",
         "/f/fleet.yaml:15: robots[1].publish[2].compression: must be one of none, zstd, "
         "deflate, got 'lz4'"),
        ("compression: zstd}", "no_drop: maybe}",
         "/f/fleet.yaml:15: robots[1].publish[2].no_drop: expected true or false"),
        # fuzzing: a quoted !!float / !!bool value is any text, and was parsed as YAML again
        ("rate_limit_hz: 1}", "rate_limit_hz: !!float \"[\"}",
         "/f/fleet.yaml:13: robots[1].publish[0].rate_limit_hz: expected a number"),
        ("compression: zstd}", "no_drop: !!bool \"[\"}",
         "/f/fleet.yaml:15: robots[1].publish[2].no_drop: expected true or false"),
        ("compression: zstd}", "no_drop: !!bool \"sure\"}",  # was read as true
         "/f/fleet.yaml:15: robots[1].publish[2].no_drop: expected true or false"),
        ("rate_limit_hz: 1}", f"rate_limit_hz: 1{'0' * 400}}}",  # float() overflowed
         "/f/fleet.yaml:13: robots[1].publish[0].rate_limit_hz: must be a finite number, "
         "got 1000"),
        ("compression: zstd}", "qos: best}",
         "/f/fleet.yaml:15: robots[1].publish[2].qos: unknown field"),
        ("{remote_topic: /husky1/map, type: nav_msgs/msg/OccupancyGrid}",
         "{remote_topic: /husky1/map, type: nav_msgs/msg/Nope}",
         "/f/fleet.yaml:17: robots[1].subscribe[0].type: unknown ROS type 'nav_msgs/msg/Nope'"),
        ("{remote_topic: /husky1/map,", "{remote_topic: /jackal2/goal_pose,",
         "/f/fleet.yaml:17: robots[1].subscribe[0].remote_topic: '/jackal2/goal_pose' is "
         "already received by command_topics[0]"),
        ("OccupancyGrid}\n", "OccupancyGrid, local_topic: /initialpose}\n",
         "/f/fleet.yaml:17: robots[1].subscribe[0].local_topic: '/initialpose' is already "
         "received by command_topics[1]"),
        ("battery_topic: /battery_state", "battery_topic: battery",
         "/f/fleet.yaml:18: robots[1].battery_topic: 'battery' is not an absolute ROS topic"),
        ("ros_domain_id: 7", "ros_domain_id: 233",
         "/f/fleet.yaml:19: robots[1].ros_domain_id: must be between 0 and 232, got 233"),
        ("rmw_implementation: rmw_cyclonedds_cpp", "rmw_implementation: rmw_fast",
         "/f/fleet.yaml:20: robots[1].rmw_implementation: unknown RMW implementation 'rmw_fast'"),
        ("location: warehouse A", "location: \"a\\nb\"",
         "/f/fleet.yaml:21: robots[1].location: must be one line of at most 200 printable "
         "characters, got 'a\\nb'"),
        ("location: warehouse A", "location: 7",
         "/f/fleet.yaml:21: robots[1].location: expected a string"),
        ("server_ip: 10.8.0.1\n", "server_ip: 10.8.0.1\nhttps_port: 8080\n",
         "/f/fleet.yaml:6: https_port: 8080 is also server_port"),
        ("server_ip: 10.8.0.1\n", "server_ip: 10.8.0.1\ntls: {cert: a.pem}\n",
         "/f/fleet.yaml:6: tls: missing required field 'key'"),
        ("name: campus\n", "name: \"a\\nb\"\n",
         "/f/fleet.yaml:2: name: fleet name 'a\\nb' must be ASCII letters, digits"),
        # issue 14: the fleet name became a root command on every robot (wg-quick PostUp)
        ("name: campus\n", "name: \"x\\n[Interface]\\nPostUp = touch /tmp/PWNED #\"\n",
         "/f/fleet.yaml:2: name: fleet name 'x\\n[Interface]\\nPostUp = touch /tmp/PWNED '... "
         "must be ASCII"),
        ("name: campus\n", "name: \"my campus\"\n", "/f/fleet.yaml:2: name: fleet name"),
        ("name: campus\n", "name: caf\u00e9\n", "/f/fleet.yaml:2: name: fleet name"),
        ("name: campus\n", "name: -x\n", "/f/fleet.yaml:2: name: fleet name"),
        ("name: campus\n", f"name: {'c' * 64}\n",
         f"/f/fleet.yaml:2: name: fleet name '{'c' * 40}'... is 64 characters long (at most 63)"),
        ("  - name: jackal2\n", f"  - name: {'j' * 64}\n",
         "/f/fleet.yaml:9: robots[1].name: robot name"),
        ("endpoint: vpn.example.com:51820\n", "endpoint: vpn.example.com:\uff15\uff11\uff18\n",
         "/f/fleet.yaml:3: endpoint: expected HOST:PORT (ASCII, port 1..65535 without"),
        ("endpoint: vpn.example.com:51820\n", "endpoint: vpn.example.com:\u00b2\n",
         "/f/fleet.yaml:3: endpoint: expected HOST:PORT"),
        ("endpoint: vpn.example.com:51820\n", "endpoint: vpn.example.com:70000\n",
         "/f/fleet.yaml:3: endpoint: expected HOST:PORT"),
        ("    ip: 10.8.0.3\n",
         "    ip: 10.8.0.3\n    mtu_bytes: !!int \"\uff11\uff12\uff18\uff10\"\n",
         "/f/fleet.yaml:11: robots[1].mtu_bytes: expected an integer"),
        ("  - email: alice@example.com\n", "  - email: \"alice\\u2028x@example.com\"\n",
         "/f/fleet.yaml:23: users[0].email: 'alice\\u2028x@example.com' is not an email"),
        ("  - email: alice@example.com\n", "  - email: \"\\ud83e@example.com\"\n",
         "/f/fleet.yaml:23: users[0].email: '\\ud83e@example.com' is not an email"),
        ("  - email: alice@example.com\n", f"  - email: {'a' * 250}@example.com\n",
         "/f/fleet.yaml:23: users[0].email: 'aaaa"),
        ("    ip: 10.8.0.3\n",
         "    ip: 10.8.0.3\n    command_topics: [{topic: go, type: x/msg/Y}]\n",
         "/f/fleet.yaml:11: robots[1].command_topics[0].type: unknown ROS type 'x/msg/Y'"),
    ],
)
def test_topic_errors_name_file_line_field(old: str, new: str, expected: str) -> None:
    assert old in TOPICS
    assert _error(TOPICS.replace(old, new, 1)).startswith(expected)


MEDIA = GOOD.replace("    extra_receive: [\"/husky1/scan\"]\n", """\
    publish:
      - {topic: /cam, type: sensor_msgs/msg/Image, video: {codec: vp8, max_bitrate_kbps: 500}}
      - {topic: /points, type: sensor_msgs/msg/PointCloud2, viewer_cloud: {}}
    tf: {rotation_delta_rad: 0.02}
""")


def test_video_viewer_cloud_and_tf_round_trip() -> None:
    from fleetctl.client.config import TfSpec, VideoSpec, ViewerCloudSpec

    fleet = parse_fleet(Path("fleet.yaml"), MEDIA)
    jackal = fleet.robots[1]
    assert jackal.publish is not None
    assert jackal.publish[0].video == VideoSpec(codec="vp8", max_bitrate_kbps=500)
    assert jackal.publish[1].viewer_cloud == ViewerCloudSpec()
    assert jackal.tf == TfSpec(rotation_delta_rad=0.02)
    assert fleet.robots[0].tf is None
    text = dump_fleet(fleet)
    assert parse_fleet(Path("fleet.yaml"), text) == fleet
    # Absent keys stay absent: a fleet without them keeps its bytes.
    assert "tf:" not in text.split("- name: jackal2")[0] and "video:" not in dump_fleet(
        parse_fleet(Path("fleet.yaml"), GOOD))


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ("codec: vp8", "codec: mjpeg",
         "/f/fleet.yaml:12: robots[1].publish[0].video.codec: must be one of h264, vp8, vp9, "
         "av1, got 'mjpeg'"),
        ("max_bitrate_kbps: 500", "max_bitrate_kbps: 50",
         "/f/fleet.yaml:12: robots[1].publish[0].video.min_bitrate_kbps: must be <= "
         "max_bitrate_kbps (50), got 100"),
        ("max_bitrate_kbps: 500", "max_bitrate_kbps: 0",
         "/f/fleet.yaml:12: robots[1].publish[0].video.max_bitrate_kbps: must be between 1"),
        ("max_bitrate_kbps: 500", "keyframe_interval_s: 0",
         "/f/fleet.yaml:12: robots[1].publish[0].video.keyframe_interval_s: must be > 0"),
        ("max_bitrate_kbps: 500", "bframes: 2",
         "/f/fleet.yaml:12: robots[1].publish[0].video.bframes: unknown field"),
        ("type: sensor_msgs/msg/Image", "type: sensor_msgs/msg/LaserScan",
         "/f/fleet.yaml:12: robots[1].publish[0].video: only for sensor_msgs/msg/Image or "
         "sensor_msgs/msg/CompressedImage, not sensor_msgs/msg/LaserScan"),
        ("type: sensor_msgs/msg/PointCloud2", "type: sensor_msgs/msg/LaserScan",
         "/f/fleet.yaml:13: robots[1].publish[1].viewer_cloud: only for "
         "sensor_msgs/msg/PointCloud2"),
        ("viewer_cloud: {}", "viewer_cloud: {resolution_m: 0.0001}",
         "/f/fleet.yaml:13: robots[1].publish[1].viewer_cloud.resolution_m: must be between "
         "0.001 and 1, got 0.0001"),
        ("{topic: /cam,", "{topic: /points/viewer,",
         "/f/fleet.yaml:13: robots[1].publish[1].viewer_cloud: its viewer topic "
         "'/points/viewer' is also publish[0]'s topic"),
        ("{topic: /cam, type: sensor_msgs/msg/Image, video: {codec: vp8, max_bitrate_kbps: 500}}",
         "{topic: /tf, type: tf2_msgs/msg/TFMessage}",
         "/f/fleet.yaml:12: robots[1].publish[0].topic: /tf is sent by the robot's tf section"),
        ("tf: {rotation_delta_rad: 0.02}", "tf: {rotation_delta_rad: 4}",
         "/f/fleet.yaml:14: robots[1].tf.rotation_delta_rad: must be between 0 and pi, got 4.0"),
        ("tf: {rotation_delta_rad: 0.02}", "tf: {max_rate_hz: 0}",
         "/f/fleet.yaml:14: robots[1].tf.max_rate_hz: must be > 0 and <= 1000, got 0.0"),
        ("tf: {rotation_delta_rad: 0.02}", "tf: {rate: 3}",
         "/f/fleet.yaml:14: robots[1].tf.rate: unknown field"),
        ("tf: {rotation_delta_rad: 0.02}", "tf: 10",
         "/f/fleet.yaml:14: robots[1].tf: expected a mapping"),
    ],
)
def test_media_errors_name_file_line_field(old: str, new: str, expected: str) -> None:
    assert old in MEDIA
    assert _error(MEDIA.replace(old, new, 1)).startswith(expected)


def test_relay_replicas_round_trip_and_only_when_set() -> None:
    one = parse_fleet(Path("fleet.yaml"), GOOD)
    assert one.relay_replicas == 1 and "relay_replicas" not in dump_fleet(one)
    two = parse_fleet(Path("fleet.yaml"), GOOD.replace("robots:\n", "relay_replicas: 2\nrobots:\n"))
    assert two.relay_replicas == 2
    assert "\nrelay_replicas: 2\n" in dump_fleet(two)
    assert parse_fleet(Path("fleet.yaml"), dump_fleet(two)) == two


@pytest.mark.parametrize(("lines", "expected"), [
    ("relay_replicas: 0\n", "/f/fleet.yaml:6: relay_replicas: must be between 1 and 8"),
    ("relay_replicas: 9\n", "/f/fleet.yaml:6: relay_replicas: must be between 1 and 8"),
    ("relay_replicas: two\n", "/f/fleet.yaml:6: relay_replicas: expected an integer"),
    # Replica i listens on server_port + i and https_port + i.
    ("relay_replicas: 4\nserver_port: 8080\nhttps_port: 8082\n",
     "/f/fleet.yaml:6: relay_replicas: 4 relay replicas listen on server_port 8080-8083 and "
     "https_port 8082-8085: the two runs overlap"),
    ("relay_replicas: 3\nhttps_port: 65534\n",
     "/f/fleet.yaml:7: https_port: 3 relay replicas need ports 65534 to 65536, past 65535"),
])
def test_bad_relay_replicas_name_the_field(lines: str, expected: str) -> None:
    assert _error(GOOD.replace("robots:\n", lines + "robots:\n")).startswith(expected)


def test_user_robots_round_trip_and_only_when_set() -> None:
    """A user without ``robots`` may use every robot, and keeps the bytes of fleets made
    before the field; with it, the list is kept in its order."""
    every = parse_fleet(Path("fleet.yaml"), GOOD)
    assert every.users[0].robots is None and "robots:\n  -" not in dump_fleet(every)
    scoped = parse_fleet(Path("fleet.yaml"), GOOD.replace(
        "    role: viewer\n", "    role: viewer\n    robots: [jackal2, husky1]\n"))
    assert scoped.users[0].robots == ("jackal2", "husky1")
    assert "  role: viewer\n  robots:\n  - jackal2\n  - husky1\n" in dump_fleet(scoped)
    assert parse_fleet(Path("fleet.yaml"), dump_fleet(scoped)) == scoped


@pytest.mark.parametrize(("robots", "role", "expected"), [
    ("robots: husky1", "viewer", "/f/fleet.yaml:15: users[0].robots: expected a list of "
     "robot names such as [husky1, jackal2], got 'husky1'"),
    ("robots:", "viewer", "/f/fleet.yaml:15: users[0].robots: expected a list of robot "
     "names, got null (leave the field out for every robot)"),
    ("robots: {husky1: true}", "viewer", "/f/fleet.yaml:15: users[0].robots: expected a list"),
    ("robots: []", "viewer", "/f/fleet.yaml:15: users[0].robots: an empty list: name at "
     "least one robot, or leave the field out for every robot"),
    ("robots: [husky1, husky9]", "viewer", "/f/fleet.yaml:15: users[0].robots[1]: no robot "
     "'husky9' in the fleet (its robots: husky1, jackal2)"),
    ("robots: [husky1, 7]", "viewer", "/f/fleet.yaml:15: users[0].robots[1]: expected a "
     "string"),
    ("robots: [husky1, husky1]", "operator", "/f/fleet.yaml:15: users[0].robots[1]: robot "
     "'husky1' is listed twice"),
    ("robots: [husky1]", "admin", "/f/fleet.yaml:15: users[0].robots: an admin may use every "
     "robot and cannot be scoped to some: remove the field, or make the user a viewer or an "
     "operator"),
])
def test_bad_user_robots_name_file_line_field(robots: str, role: str, expected: str) -> None:
    text = GOOD.replace("    role: viewer\n", f"    role: {role}\n    {robots}\n")
    assert _error(text) == expected
