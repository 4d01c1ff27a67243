"""``fleetctl status`` shows a replay's robot (``NAME_replay``, what ``fleetctl replay``
renames a recorded robot to) as a replay, not as a robot removed from fleet.yaml."""

from __future__ import annotations

from fleetctl.deploy import composerun


def test_a_replayed_robot_is_shown_as_a_replay_not_as_removed() -> None:
    robots = [{"name": "husky1", "online": True, "last_seen_s": None},
              {"name": "husky1_replay", "online": True, "last_seen_s": None},
              {"name": "rover3", "online": False, "last_seen_s": None}]
    report = composerun.StatusReport((), robots, fleet_robots=frozenset({"husky1"}))
    lines = {line.split()[0]: line for line in report.render_text().splitlines() if line}
    assert lines["husky1_replay"].endswith("  (replay of husky1)")
    assert lines["rover3"].endswith("  (not in fleet.yaml: removed)")
    assert [(r["in_fleet"], r["replay_of"]) for r in report.to_json()["robots"]] == [
        (True, None), (False, "husky1"), (False, None)]
