from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.errors import ConfigError
from fleetctl.server.registry import FORGET_AT_ONCE, MAX_ROBOTS, RobotRegistry, robot_name
from tests.support import ManualClock


def test_robot_name() -> None:
    assert robot_name("/husky1/scan") == "husky1"
    assert robot_name("/husky1/camera/image") == "husky1"
    assert robot_name("/status") is None and robot_name("husky1/scan") is None
    assert robot_name("//scan") is None


def test_online_offline_and_persistence(tmp_path: Path) -> None:
    clock = ManualClock(1_000.0)
    db = tmp_path / "fleet.db"
    reg = RobotRegistry(db, offline_after_s=5.0, clock=clock)
    reg.seen("husky1")
    reg.attach("husky1")
    reg.seen("husky2")
    reg.attach("husky2")
    reg.set_status("husky1", "driving", True, 0.8, "lab")
    assert reg.online("husky1")
    clock.now_s += 6
    assert not reg.online("husky1")  # silent too long
    reg.seen("husky2")
    reg.detach("husky2")
    assert not reg.online("husky2")  # no connection speaks for it
    assert reg.flush() == 2
    reg.close()
    again = RobotRegistry(db, offline_after_s=5.0, clock=clock)
    rec = again.get("husky1")
    assert rec is not None and rec.status == "driving" and rec.is_ok is True
    assert rec.battery_level == 0.8 and rec.location == "lab"
    assert rec.last_seen_s == 1000.0
    assert [r["name"] for r in again.as_json()] == ["husky1", "husky2"]
    assert not any(r["online"] for r in again.as_json())
    again.close()


@pytest.mark.parametrize("kind", ["text", "directory"])
def test_a_database_path_that_is_no_database_is_a_config_error(tmp_path: Path,
                                                                kind: str) -> None:
    path = tmp_path / "fleet.db"
    if kind == "text":
        path.write_text("not a database\n")
    else:
        path.mkdir()
    with pytest.raises(ConfigError, match=r"fleet\.db: field 'database' of the server config"):
        RobotRegistry(path, 5.0)


def test_a_battery_the_robot_does_not_know_is_none(tmp_path: Path) -> None:
    """The client sends -1 for a robot without a battery topic: unknown, not -100 %."""
    db = tmp_path / "fleet.db"
    reg = RobotRegistry(db, offline_after_s=5.0, clock=ManualClock(1_000.0))
    for name, level in (("husky1", -1.0), ("husky2", float("nan")), ("husky3", 0.0)):
        reg.seen(name)
        reg.set_status(name, "OK", True, level, "")
    assert [r["battery_level"] for r in reg.as_json()] == [None, None, 0.0]
    reg.flush()
    reg.close()
    # A row written as -1 by an older server reads back as unknown too.
    import sqlite3
    with sqlite3.connect(db) as con:
        con.execute("UPDATE robots SET battery_level = -1 WHERE name = 'husky3'")
    again = RobotRegistry(db, offline_after_s=5.0, clock=ManualClock(1_000.0))
    assert [r["battery_level"] for r in again.as_json()] == [None, None, None]
    again.close()


def test_a_full_registry_forgets_the_robots_seen_longest_ago(tmp_path: Path) -> None:
    # It refused every new name for good (kept across restarts): after 10,000 names a
    # fleet whose robots come and go stopped showing new robots (the relay soak, with a
    # new robot name every few seconds, gets there in hours).
    clock = ManualClock(1_000.0)
    db = tmp_path / "fleet.db"
    reg = RobotRegistry(db, offline_after_s=5.0, clock=clock)
    reg.seen("connected")  # the oldest, but a connection still speaks for it
    reg.attach("connected")
    for k in range(MAX_ROBOTS - 1):
        clock.now_s += 1
        reg.seen(f"gone{k}")
    reg.flush()
    clock.now_s += 1
    assert reg.seen("newcomer") and reg.get("newcomer") is not None
    assert reg.get("connected") is not None  # live robots are never forgotten
    assert reg.get("gone0") is None and reg.get(f"gone{FORGET_AT_ONCE - 1}") is None
    assert reg.get(f"gone{FORGET_AT_ONCE}") is not None
    assert len(reg.names()) == MAX_ROBOTS - FORGET_AT_ONCE + 1
    assert reg.forgotten_names == FORGET_AT_ONCE and reg.dropped_names == 0
    reg.seen("gone1")  # a forgotten robot that comes back is a robot like any other
    reg.close()
    again = RobotRegistry(db, offline_after_s=5.0, clock=clock)
    assert "gone0" not in again.names() and {"gone1", "newcomer"} <= set(again.names())
    assert len(again.names()) == MAX_ROBOTS - FORGET_AT_ONCE + 2
    again.close()
