"""Named sessions' subscriptions in SQLite (the ``sessions`` table of the registry database).

Only the subscription patterns are stored; the mailboxes stay in memory. Changes are
written behind: the session table collects the latest state of each changed session and
:meth:`SessionStore.write` stores them in one transaction, off the event loop (the server
does it about once a second, in a worker thread, and at shutdown), so a client toggling
subscriptions never makes the relay wait for a disk commit. A row is the key
``(identities, name)`` -- the sorted identity names of the connection, as JSON, and the
session name -- and its patterns in the order they were subscribed.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass

_SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    identities TEXT NOT NULL,
    name TEXT NOT NULL,
    patterns TEXT NOT NULL,
    updated_s REAL NOT NULL,
    PRIMARY KEY (identities, name)
)
"""


@dataclass(frozen=True)
class StoredSession:
    """One row of the ``sessions`` table.

    Attributes:
        identities: Sorted identity names of the session's key.
        name: The session name the client chose.
        patterns: Subscription regexes, in subscription order.
        updated_s: Wall clock (seconds since the epoch) of the last change.
    """

    identities: tuple[str, ...]
    name: str
    patterns: tuple[str, ...]
    updated_s: float


class SessionStore:
    """Reads and writes the ``sessions`` table.

    Args:
        db: An open SQLite connection (the robot registry's); the table is created if
            missing. The store never closes it.
        clock: Wall clock in seconds (``updated_s``).

    Raises:
        sqlite3.Error: From every method, when the database fails; callers log it and go on.
    """

    def __init__(self, db: sqlite3.Connection, clock: Callable[[], float] = time.time) -> None:
        self._db = db
        self._clock = clock
        with self._db:
            self._db.execute(_SCHEMA)

    def load(self) -> list[StoredSession]:
        """Return every stored session; rows that do not parse are deleted."""
        out: list[StoredSession] = []
        bad: list[tuple[str, str]] = []
        rows = self._db.execute("SELECT identities, name, patterns, updated_s FROM sessions")
        for ids_json, name, patterns_json, updated_s in rows.fetchall():
            try:
                ids, patterns = json.loads(ids_json), json.loads(patterns_json)
            except ValueError:
                bad.append((ids_json, name))
                continue
            if not (_strings(ids) and _strings(patterns) and isinstance(name, str)):
                bad.append((ids_json, name))
                continue
            out.append(StoredSession(tuple(ids), name, tuple(patterns), float(updated_s)))
        if bad:
            with self._db:
                self._db.executemany(
                    "DELETE FROM sessions WHERE identities = ? AND name = ?", bad)
        return out

    def save(self, identities: tuple[str, ...], name: str, patterns: list[str]) -> None:
        """Insert or replace the patterns of session ``(identities, name)``."""
        with self._db:
            self._db.execute(
                "INSERT OR REPLACE INTO sessions (identities, name, patterns, updated_s) "
                "VALUES (?, ?, ?, ?)",
                (_key(identities), name, json.dumps(patterns), self._clock()),
            )

    def write(self, changes: list[tuple[tuple[str, ...], str, tuple[str, ...] | None]]) -> None:
        """Store several sessions in one transaction.

        Args:
            changes: ``(identities, name, patterns)``; ``patterns`` ``None`` deletes the row.
        """
        now = self._clock()
        upserts = [(_key(i), n, json.dumps(list(p)), now) for i, n, p in changes if p is not None]
        deletes = [(_key(i), n) for i, n, p in changes if p is None]
        with self._db:
            self._db.executemany(
                "INSERT OR REPLACE INTO sessions (identities, name, patterns, updated_s) "
                "VALUES (?, ?, ?, ?)", upserts)
            self._db.executemany("DELETE FROM sessions WHERE identities = ? AND name = ?",
                                 deletes)

    def delete(self, identities: tuple[str, ...], name: str) -> None:
        """Forget session ``(identities, name)`` (no error if it is not stored)."""
        with self._db:
            self._db.execute("DELETE FROM sessions WHERE identities = ? AND name = ?",
                             (_key(identities), name))


def _key(identities: tuple[str, ...]) -> str:
    return json.dumps(sorted(identities))


def _strings(value: object) -> bool:
    return isinstance(value, list) and all(isinstance(v, str) for v in value)
