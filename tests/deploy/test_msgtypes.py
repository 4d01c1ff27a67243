"""The fleet's own message types (FLEET/msg_types/PKG/msg/NAME.msg) in fleet.yaml's check:
accepted, unknown, definitions that are bad, names that are not ROS names."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from fleetctl.cli.main import main
from fleetctl.client.config import load_client_config
from fleetctl.deploy.fleet import load_fleet, parse_fleet
from fleetctl.deploy.msgtypes import MAX_MSG_BYTES, MAX_MSG_FILES, load_msg_types
from fleetctl.errors import ConfigError

FLEET = """\
version: 1
name: yard
subnet: 10.8.0.0/24
server_ip: 10.8.0.1
robots:
  - name: husky1
    ip: 10.8.0.2
    publish:
      - {topic: /robot_status, type: %s}
    subscribe:
      - {remote_topic: /base/mission, type: %s}
"""

STATUS = """\
# The robot's own status (a comment line, as rosidl allows)
uint8 MODE_IDLE=0
uint8 MODE_DRIVING=1
std_msgs/Header header
uint8 mode
Battery battery
float32[] motor_temperatures_c
string note "none"
"""
BATTERY = "float32 voltage_v\nfloat32 charge_ratio\n"
MISSION = "string name\ngeometry_msgs/PoseStamped[] waypoints\n"


def _fleet(root: Path, publish_type: str = "my_robot_msgs/msg/Status",
           subscribe_type: str = "base_msgs/Mission") -> Path:
    root.mkdir(exist_ok=True)
    (root / "fleet.yaml").write_text(FLEET % (publish_type, subscribe_type))
    return root


def _msg(root: Path, relpath: str, text: str) -> Path:
    path = root / "msg_types" / relpath
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def write_own_packages(root: Path) -> None:
    _msg(root, "my_robot_msgs/msg/Status.msg", STATUS)
    _msg(root, "my_robot_msgs/msg/Battery.msg", BATTERY)
    _msg(root, "base_msgs/msg/Mission.msg", MISSION)


def _load_error(root: Path) -> str:
    with pytest.raises(ConfigError) as info:
        load_fleet(root)
    return str(info.value)


def test_own_types_are_accepted_with_their_dependencies(tmp_path: Path) -> None:
    root = _fleet(tmp_path / "fleet")
    write_own_packages(root)
    # What rosidl installs beside each .msg, a README and a service: left alone.
    _msg(root, "my_robot_msgs/msg/Status.idl", "module my_robot_msgs { ... };\n")
    _msg(root, "my_robot_msgs/srv/Reset.srv", "---\nbool ok\n")
    (root / "msg_types" / "README.md").write_text("copied from ~/ws/install\n")
    (root / "msg_types" / ".git").mkdir()
    fleet = load_fleet(root)
    robot = fleet.robots[0]
    assert robot.publish is not None and robot.publish[0].type == "my_robot_msgs/msg/Status"
    assert fleet.msg_types.names == {"my_robot_msgs/msg/Status", "my_robot_msgs/msg/Battery",
                                     "base_msgs/msg/Mission"}
    assert dict(fleet.msg_types.texts)["my_robot_msgs/msg/Battery"] == BATTERY


def test_no_msg_types_directory_means_no_own_types(tmp_path: Path) -> None:
    root = _fleet(tmp_path / "fleet", "std_msgs/msg/String", "std_msgs/String")
    assert load_fleet(root).msg_types.names == frozenset()
    assert load_msg_types(root).directory == root / "msg_types"


def test_unknown_type_says_where_it_looked_and_what_to_do(tmp_path: Path) -> None:
    root = _fleet(tmp_path / "fleet", "my_robot_msgs/msg/Statu")
    write_own_packages(root)
    assert _load_error(root) == (
        f"{root}/fleet.yaml:9: robots[0].publish[0].type: unknown ROS type "
        "'my_robot_msgs/msg/Statu': not a ROS 2 Jazzy or fleetctl type, and the fleet's own "
        f"definitions do not have it ({root}/msg_types/my_robot_msgs/msg/Statu.msg). Did you "
        "mean my_robot_msgs/msg/Status? A package of your own: copy its msg/ folder (in its "
        "workspace: install/my_robot_msgs/share/my_robot_msgs/msg) to "
        "FLEET/msg_types/my_robot_msgs/msg/, then render")


def test_fleet_yaml_text_alone_knows_the_default_types_only(tmp_path: Path) -> None:
    # Without its directory (parse_fleet of the text) an own type is unknown.
    with pytest.raises(ConfigError, match=r"publish\[0\]\.type: unknown ROS type "
                                          r"'my_robot_msgs/msg/Status'.*FLEET/msg_types/"
                                          r"my_robot_msgs/msg/Status\.msg"):
        parse_fleet(Path("fleet.yaml"), FLEET % ("my_robot_msgs/msg/Status", "std_msgs/String"))


def test_an_own_type_of_a_command_topic_and_subscribe_entry_is_checked(tmp_path: Path) -> None:
    root = _fleet(tmp_path / "fleet", "std_msgs/msg/String", "base_msgs/msg/Missing")
    write_own_packages(root)
    assert "robots[0].subscribe[0].type: unknown ROS type 'base_msgs/msg/Missing'" in (
        _load_error(root))


@pytest.mark.parametrize(("relpath", "text", "expected"), [
    ("my_robot_msgs/msg/Status.msg", "uint8 mode\nint32[ broken\n",
     "my_robot_msgs/msg/Status.msg:2: cannot parse 'int32[ broken' (a line is 'TYPE name', "
     "'TYPE name DEFAULT' or 'TYPE NAME=VALUE')"),
    ("my_robot_msgs/msg/Status.msg", "uint8 mode\n---\nbool ok\n",
     "my_robot_msgs/msg/Status.msg:2: cannot parse '---'"),
    ("my_robot_msgs/msg/Status.msg", "uint8 mode\nWheel[] wheels\n",
     "my_robot_msgs/msg/Status.msg:2: field 'wheels': unknown message type "
     "my_robot_msgs/msg/Wheel"),
    ("my_robot_msgs/msg/Status.msg", "uint8 mode\nfloat64 Speed\n",
     "my_robot_msgs/msg/Status.msg:2: field 'Speed': not a ROS field name"),
    ("my_robot_msgs/msg/Status.msg", "uint8 idle=0\n",
     "my_robot_msgs/msg/Status.msg:1: cannot parse 'uint8 idle=0'"),
    ("my_robot_msgs/msg/Status.msg",
     "uint8 mode\n" + "=" * 80 + "\nMSG: std_msgs/Sneaky\nint32 x\n",
     "my_robot_msgs/msg/Status.msg: defines std_msgs/msg/Sneaky too: one message per file"),
    ("std_msgs/msg/String.msg", "string data\n",
     "std_msgs/msg/String.msg: std_msgs/msg/String is a ROS 2 Jazzy or fleetctl type already"),
])
def test_a_bad_definition_names_the_file_and_line(tmp_path: Path, relpath: str, text: str,
                                                   expected: str) -> None:
    root = _fleet(tmp_path / "fleet", "std_msgs/msg/String", "std_msgs/String")
    _msg(root, relpath, text)
    error = _load_error(root)
    assert error.startswith(f"{root}/msg_types/{expected}"), error
    assert "\n" not in error


@pytest.mark.parametrize(("relpath", "expected"), [
    ("My_Msgs/msg/Status.msg", "My_Msgs: 'My_Msgs' is not a ROS package name (REP 144"),
    ("my__msgs/msg/Status.msg", "my__msgs: 'my__msgs' is not a ROS package name"),
    ("m/msg/Status.msg", "m: 'm' is not a ROS package name"),
    ("my-msgs/msg/Status.msg", "my-msgs: 'my-msgs' is not a ROS package name"),
    ("my_msgs/msg/status.msg", "my_msgs/msg/status.msg: 'status' is not a ROS message name"),
    ("my_msgs/msg/Sta tus.msg", "my_msgs/msg/Sta tus.msg: 'Sta tus' is not a ROS message "),
    ("my_msgs/msg/Status..msg", "my_msgs/msg/Status..msg: 'Status.' is not a ROS message "),
])
def test_names_that_are_not_ros_names_are_refused(tmp_path: Path, relpath: str,
                                                  expected: str) -> None:
    root = _fleet(tmp_path / "fleet", "std_msgs/msg/String", "std_msgs/String")
    _msg(root, relpath, "int32 x\n")
    assert _load_error(root).startswith(f"{root}/msg_types/{expected}")


def test_files_that_are_not_small_regular_utf8_files_are_refused(tmp_path: Path) -> None:
    root = _fleet(tmp_path / "fleet", "std_msgs/msg/String", "std_msgs/String")
    big = _msg(root, "my_msgs/msg/Big.msg", "# padding\n" * (MAX_MSG_BYTES // 10 + 1))
    assert _load_error(root) == f"{big}: cannot read: larger than {MAX_MSG_BYTES} bytes"
    big.write_bytes(b"string \xff\n")
    assert _load_error(root) == f"{big}: cannot read: not UTF-8 text"
    big.unlink()
    os.symlink("/dev/zero", big)
    assert _load_error(root) == f"{big}: cannot read: not a regular file"


def test_at_most_max_msg_files_are_read(tmp_path: Path) -> None:
    root = _fleet(tmp_path / "fleet", "std_msgs/msg/String", "std_msgs/String")
    for i in range(MAX_MSG_FILES + 1):
        _msg(root, f"my_msgs/msg/M{i}.msg", "int32 x\n")
    assert _load_error(root) == (f"{root}/msg_types: more than {MAX_MSG_FILES} .msg files "
                                 "(copy the msg/ folders of the fleet's own packages only)")


def test_msg_types_that_is_a_file_is_refused(tmp_path: Path) -> None:
    root = _fleet(tmp_path / "fleet", "std_msgs/msg/String", "std_msgs/String")
    (root / "msg_types").write_text("my_msgs/Status\n")
    assert _load_error(root).startswith(f"{root}/msg_types: not a directory")


# --- through the command line: init, add-robot, fleet.yaml by hand, render -------------


def _robot_workspace(root: Path) -> Path:
    """The robot's built workspace: install/<pkg> with share/<pkg>/msg, as colcon makes it."""
    for relpath, text in (("Status.msg", STATUS), ("Battery.msg", BATTERY)):
        path = root / "install" / "my_robot_msgs" / "share" / "my_robot_msgs" / "msg" / relpath
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root / "install" / "my_robot_msgs"


def test_render_writes_a_client_yaml_the_robot_client_loads(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    fleet_dir = tmp_path / "yard"
    assert main(["init", str(fleet_dir)]) == 0
    assert main(["add-robot", "husky1", "--fleet", str(fleet_dir)]) == 0
    fleet_yaml = fleet_dir / "fleet.yaml"
    fleet_yaml.write_text(fleet_yaml.read_text().replace("  subscribe: []\n", (
        "  publish:\n"
        "  - {topic: /robot_status, type: my_robot_msgs/msg/Status, priority: 2.0}\n"
        "  subscribe: []\n")))
    capsys.readouterr()

    assert main(["render", "--fleet", str(fleet_dir)]) == 3
    err = capsys.readouterr().err
    assert "robots[0].publish[0].type: unknown ROS type 'my_robot_msgs/msg/Status'" in err
    assert "Traceback" not in err

    write_own_packages(fleet_dir)
    assert main(["render", "--fleet", str(fleet_dir)]) == 0
    client_yaml = fleet_dir / "robots" / "husky1" / "client.yaml"
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(_robot_workspace(tmp_path / "ws")))
    config = load_client_config(client_yaml)
    assert [(p.topic, p.type, p.priority) for p in config.publish] == [
        ("/robot_status", "my_robot_msgs/msg/Status", 2.0)]
