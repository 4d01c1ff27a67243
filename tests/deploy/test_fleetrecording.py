"""fleet.yaml's ``recording:`` section: read, checked as the server checks it, written back,
rendered into a server.yaml the server loads."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from fleetctl.deploy import operations as ops
from fleetctl.deploy.fleet import dump_fleet, parse_fleet
from fleetctl.deploy.fleetrecording import (
    DEFAULT_MAX_FILE_BYTES,
    DEFAULT_MAX_TOTAL_BYTES,
    FleetRecording,
)
from fleetctl.errors import ConfigError
from fleetctl.server.config import load_server_config
from tests.deploy.test_fleet import GOOD

SECTION = 'recording:\n  topics: ["/.*/map", "/husky1/.*"]\n'


def _error(text: str) -> str:
    with pytest.raises(ConfigError) as info:
        parse_fleet(Path("/f/fleet.yaml"), GOOD + text)
    return str(info.value)


def test_section_is_read_with_defaults_and_written_back() -> None:
    fleet = parse_fleet(Path("fleet.yaml"), GOOD + SECTION)
    assert fleet.recording == FleetRecording(("/.*/map", "/husky1/.*"),
                                             DEFAULT_MAX_TOTAL_BYTES, DEFAULT_MAX_FILE_BYTES)
    again = parse_fleet(Path("fleet.yaml"), dump_fleet(fleet))
    assert again == fleet
    assert parse_fleet(Path("fleet.yaml"), GOOD + "recording: null\n").recording is None
    assert "recording" not in dump_fleet(parse_fleet(Path("fleet.yaml"), GOOD))
    bounded = parse_fleet(Path("fleet.yaml"), GOOD + SECTION + "  max_total_bytes: 4194304\n"
                          "  max_file_bytes: 2097152\n  max_age_s: 86400\n")
    assert bounded.recording == FleetRecording(("/.*/map", "/husky1/.*"), 4194304, 2097152,
                                               86400)
    assert parse_fleet(Path("fleet.yaml"), dump_fleet(bounded)) == bounded
    # A small budget without a file size: files of half the budget, not an error about a
    # default the operator never wrote.
    small = parse_fleet(Path("fleet.yaml"), GOOD + SECTION + "  max_total_bytes: 104857600\n")
    assert small.recording is not None and small.recording.max_file_bytes == 52428800


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("recording:\n  topics: []\n",
         "/f/fleet.yaml:{2}: recording.topics: list at least one topic pattern"),
        ("recording:\n  max_age_s: 60\n",
         "/f/fleet.yaml:{2}: recording: missing required field 'topics'"),
        ('recording:\n  topics: ["("]\n',
         "/f/fleet.yaml:{2}: recording.topics[0]: not a valid RE2 regex '('"),
        ('recording:\n  topics: ["/a", ""]\n',
         "/f/fleet.yaml:{2}: recording.topics[1]: empty pattern"),
        ('recording:\n  topics: ["/' + "a" * 4096 + '"]\n',
         "/f/fleet.yaml:{2}: recording.topics[0]: not a valid RE2 regex '/aaa"),
        ('recording:\n  topics: [".*"]\n  max_file_bytes: 8388608\n  max_total_bytes: 8388608\n',
         "/f/fleet.yaml:{3}: recording.max_file_bytes: 8388608 is more than half of "
         "max_total_bytes"),
        ('recording:\n  topics: [".*"]\n  max_file_bytes: 1000\n',
         "/f/fleet.yaml:{3}: recording.max_file_bytes: must be between 1048576 and"),
        ('recording:\n  topics: [".*"]\n  max_age_s: 1.5\n',
         "/f/fleet.yaml:{3}: recording.max_age_s: expected an integer"),
        ('recording:\n  topics: [".*"]\n  directory: /etc\n',
         "/f/fleet.yaml:{3}: recording.directory: unknown field"),
        ('recording:\n  topics: "/.*"\n', "/f/fleet.yaml:{2}: recording.topics: expected a list"),
        ("recording:\n  topics:\n" + '    - "/a"\n' * 65,
         "/f/fleet.yaml:{3}: recording.topics: 65 patterns; at most 64"),
    ],
    ids=["no-topics", "topics-missing", "bad-regex", "empty-regex", "long-regex", "file-over-half",
         "file-too-small", "age-not-integer", "directory-not-a-field", "topics-not-a-list",
         "too-many-topics"],
)
def test_errors_name_file_line_and_field(text: str, expected: str) -> None:
    # {1}: the section's first line (it follows GOOD), {2} the next, ...
    lines = GOOD.count("\n")
    assert _error(text).startswith(expected.format(*range(lines, lines + 4)))


def test_rendered_server_yaml_records_and_the_server_loads_it(fleet_dir: Path) -> None:
    path = fleet_dir / "fleet.yaml"
    # A pattern with YAML and shell metacharacters: escaped for YAML, read back as written.
    hostile = "/husky1/(scan|odom)#x: \"q\" \\d{2}"
    path.write_text(path.read_text() + "recording:\n  topics:\n"
                    f"    - {yaml.safe_dump(hostile, default_style=chr(34)).strip()}\n"
                    "  max_age_s: 604800\n")
    ops.render_fleet(fleet_dir)
    server = load_server_config(fleet_dir / "server" / "server.yaml")
    assert server.recording is not None
    assert [rule.topic for rule in server.recording.rules] == [hostile]
    assert server.recording.rules[0].identities == ()
    assert server.recording.directory == fleet_dir / "server" / "recordings"
    assert (server.recording.max_age_s, server.recording.max_total_bytes) == (
        604800.0, DEFAULT_MAX_TOTAL_BYTES)
    # fleetctl's own rewrites of fleet.yaml keep the section.
    ops.set_relay_replicas(fleet_dir, 2)
    assert parse_fleet(path, path.read_text()).recording == FleetRecording(
        (hostile,), max_age_s=604800)
