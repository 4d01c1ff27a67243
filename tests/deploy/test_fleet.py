"""fleet.yaml: round trip, and errors that name the file, the line and the field."""

from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.deploy.fleet import dump_fleet, load_fleet, parse_fleet
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
        ("endpoint: vpn.example.com:51820\n", "endpoint: vpn.example.com\n",
         "/f/fleet.yaml:3: endpoint: expected HOST:PORT"),
        ("version: 1\n", "version: 2\n", "/f/fleet.yaml:1: version: unsupported version 2"),
        ("name: campus\n", "", "/f/fleet.yaml:1: (document): missing required field 'name'"),
        ("    ip: 10.8.0.2\n", "    ip: 10.8.0.2\n    mtu_bytes: big\n",
         "/f/fleet.yaml:9: robots[0].mtu_bytes: expected an integer"),
        ("  - name: husky1\n", "  - name: [husky1]\n",
         "/f/fleet.yaml:7: robots[0].name: expected a string"),
    ],
)
def test_semantic_errors_name_file_line_field(old: str, new: str, expected: str) -> None:
    assert old in GOOD
    assert _error(GOOD.replace(old, new, 1)).startswith(expected)


def test_yaml_syntax_error_names_line() -> None:
    message = _error(GOOD.replace("  - name: husky1\n", "  - name: husky1\n bad: [\n"))
    assert message.startswith("/f/fleet.yaml:")
    assert "not valid YAML" in message


def test_empty_and_non_mapping() -> None:
    assert _error("") == "/f/fleet.yaml:1: the file is empty"
    assert _error("- 1\n").startswith("/f/fleet.yaml:1: (document): expected a mapping")


def test_missing_directory_and_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        load_fleet(tmp_path / "nope")
    with pytest.raises(ConfigError, match=r"fleet\.yaml: not found"):
        load_fleet(tmp_path)
