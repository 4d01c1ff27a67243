"""is_latched: a channel's rosbag2 QoS metadata read back."""

from __future__ import annotations

import pytest

from fleetctl.server.recording.latched import is_latched
from fleetctl.server.recording.mcapfile import _QOS


@pytest.mark.parametrize(("profiles", "latched"), [
    (_QOS % "transient_local", True),  # as the recorder writes a latched topic
    (_QOS % "volatile", False),
    ("- durability: 1\n", True),  # rosbag2 before Iron: the enum's number
    ("- durability: 2\n", False),
    ("", False),
    ("[unclosed", False),  # not YAML
    ("durability: transient_local\n", False),  # not a list of profiles
])
def test_transient_local_profiles_are_latched(profiles: str, latched: bool) -> None:
    assert is_latched({"offered_qos_profiles": profiles}) is latched


def test_no_profiles_is_not_latched() -> None:
    assert not is_latched({})
