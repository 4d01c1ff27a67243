"""Where ``fleetctl replay`` sends each recorded topic (fleetctl/cli/replaytopics.py)."""

from __future__ import annotations

import pytest

from fleetctl.cli.replaytopics import notice, renames, sent_topic


@pytest.mark.parametrize(("topic", "remap", "onto_live", "sent"), [
    ("/husky1/goal_pose", (), False, "/husky1_replay/goal_pose"),
    # One segment: a robot may subscribe to any topic (client.yaml's subscribe:).
    ("/tf", (), False, "/tf_replay"),
    ("/fleet/mission/next", (), False, "/fleet_replay/mission/next"),
    # An explicit --remap is the user's choice, first match wins, before any renaming.
    ("/husky1/scan", (("/husky1", "/ghost1"),), False, "/ghost1/scan"),
    ("/husky2/scan", (("/husky1", "/ghost1"),), False, "/husky2_replay/scan"),
    ("/husky10/scan", (("/husky1", "/ghost1"),), False, "/husky10_replay/scan"),
    ("/husky1/scan", (), True, "/husky1/scan"),
    ("/husky1/scan", (("/husky1", "/ghost1"),), True, "/ghost1/scan"),
])
def test_sent_topic(topic: str, remap: tuple[tuple[str, str], ...], onto_live: bool,
                    sent: str) -> None:
    assert sent_topic(topic, remap, onto_live) == sent


def test_the_notice_names_each_renamed_prefix_once() -> None:
    topics = {"/husky2/scan", "/husky1/scan", "/husky1/goal_pose", "/ghost/x", "/tf"}
    assert renames(topics, (("/ghost", "/g2"),)) == {
        "/husky1": "/husky1_replay", "/husky2": "/husky2_replay", "/tf": "/tf_replay"}
    line = notice(topics, (("/ghost", "/g2"),), False)
    assert line is not None and "/husky1 -> /husky1_replay, /husky2 -> /husky2_replay, " \
        "/tf -> /tf_replay (" in line
    assert notice({"/husky1/scan"}, (("/husky1", "/ghost1"),), False) is None
    assert notice({"/husky1/scan"}, (("/husky1", "/ghost1"),), True) is None
