"""The ``recording:`` section of server.yaml: defaults, paths, and clear errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from fleetctl.errors import ConfigError
from fleetctl.server.config import parse_server_config
from fleetctl.server.recording.config import MIB, RecordingRule

PATH = Path("/etc/fleet/server.yaml")


def parse(recording: Any) -> Any:
    return parse_server_config({"auth_map": "auth.yaml", "recording": recording}, PATH)


def test_no_section_means_no_recording() -> None:
    assert parse_server_config({"auth_map": "auth.yaml"}, PATH).recording is None


def test_section_parsed_with_defaults_and_relative_directory() -> None:
    cfg = parse({"directory": "rec", "rules": [{"topic": "/husky1/.*",
                                                "identities": ["husky1"]},
                                               {"topic": ".*/status"}],
                 "max_age_s": 600}).recording
    assert cfg.directory == Path("/etc/fleet/rec")
    assert cfg.rules == (RecordingRule("/husky1/.*", ("husky1",)), RecordingRule(".*/status"))
    assert cfg.max_file_bytes == 256 * MIB and cfg.max_total_bytes == 10 * 1024 * MIB
    assert cfg.rotate_after_s == 300.0  # half of max_age_s: the age bound deletes in slices


@pytest.mark.parametrize(("recording", "field"), [
    ("rec", "'recording' must be a mapping"),
    ({"rules": [{"topic": ".*"}]}, "'recording.directory' is required"),
    ({"directory": "r"}, "'recording.rules' must be a non-empty list"),
    ({"directory": "r", "rules": []}, "'recording.rules' must be a non-empty list"),
    ({"directory": "r", "rules": ["x"]}, "'recording.rules[0]' must be a mapping"),
    ({"directory": "r", "rules": [{"topic": "(("}]}, "'recording.rules[0].topic': bad RE2"),
    ({"directory": "r", "rules": [{"topic": ".*", "identities": "husky1"}]},
     "'recording.rules[0].identities' must be a list"),
    ({"directory": "r", "rules": [{"topic": ".*", "op": "send"}]},
     "unknown field 'recording.rules[0].op'"),
    ({"directory": "r", "rules": [{"topic": ".*"}], "max_total_byte": 1},
     "unknown field 'recording.max_total_byte'"),
    ({"directory": "r", "rules": [{"topic": ".*"}], "max_file_bytes": -1},
     "'recording.max_file_bytes' must be a positive integer"),
    ({"directory": "r", "rules": [{"topic": ".*"}], "max_file_bytes": 1.5},
     "'recording.max_file_bytes' must be a positive integer"),
    ({"directory": "r", "rules": [{"topic": ".*"}], "max_age_s": "1d"},
     "'recording.max_age_s' must be a positive number"),
    ({"directory": "r", "rules": [{"topic": ".*"}], "max_age_s": 10**400},  # OverflowError
     "'recording.max_age_s' must be a positive number"),
    ({"directory": "r", "rules": [{"topic": ".*"}], "max_age_s": float("nan")},
     "'recording.max_age_s' must be a positive number"),
    ({"directory": "r", "rules": [{"topic": ".*"}], "max_file_duration_s": float("inf")},
     "'recording.max_file_duration_s' must be a positive number"),
    ({"directory": "r", "rules": [{"topic": ".*"}], "worker_priority": "low"},
     "'recording.worker_priority' must be idle or normal"),
    ({"directory": "r", "rules": [{"topic": ".*"}], "max_file_bytes": 600,
      "max_total_bytes": 1000}, "'recording.max_file_bytes' must be at most half"),
])
def test_bad_input_names_the_file_and_the_field(recording: Any, field: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse(recording)
    assert str(err.value).startswith(f"{PATH}: ")
    assert field in str(err.value)
