from __future__ import annotations

import sqlite3
from pathlib import Path

from fleetctl.server.sessionstore import SessionStore, StoredSession


def test_save_load_replace_delete(tmp_path: Path) -> None:
    db = sqlite3.connect(str(tmp_path / "fleet.db"))
    store = SessionStore(db, clock=lambda: 42.0)
    store.save(("husky1",), "husky1", ["/husky1/goal_pose", "/husky1/(a|b)"])
    store.save(("alice", "husky1"), "console", [".*"])
    store.save(("husky1",), "husky1", ["/husky1/goal_pose"])  # replaces
    db.close()
    again = SessionStore(sqlite3.connect(str(tmp_path / "fleet.db")))
    assert sorted(again.load(), key=lambda s: s.name) == [
        StoredSession(("alice", "husky1"), "console", (".*",), 42.0),
        StoredSession(("husky1",), "husky1", ("/husky1/goal_pose",), 42.0),
    ]
    again.delete(("husky1",), "husky1")
    again.delete(("nobody",), "x")  # absent: no error
    assert [s.name for s in again.load()] == ["console"]


def test_rows_that_do_not_parse_are_deleted() -> None:
    db = sqlite3.connect(":memory:")
    store = SessionStore(db)
    store.save(("bob",), "good", ["/a"])
    db.execute("INSERT INTO sessions VALUES ('not json', 'bad', '[]', 0)")
    db.execute("""INSERT INTO sessions VALUES ('["bob"]', 'worse', '{"a": 1}', 0)""")
    assert [s.name for s in store.load()] == ["good"]
    assert db.execute("SELECT COUNT(*) FROM sessions").fetchone() == (1,)
