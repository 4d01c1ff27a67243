"""Robot registry: robots seen, online/offline, last status, last seen; kept in SQLite.

The relay calls :meth:`RobotRegistry.seen` on every frame from a robot, so that call only
touches memory; :meth:`RobotRegistry.flush` writes changed rows in one transaction (the
server calls it about once a second and at shutdown). A robot's name is the first path
segment of its topics (``/husky1/scan`` -> ``husky1``), so several robots may share one
NAT'd address.
"""

from __future__ import annotations

import logging
import sqlite3
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from fleetctl.errors import ConfigError
from fleetctl.wire.control import known_battery

log = logging.getLogger("fleetctl.server.registry")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS robots (
    name TEXT PRIMARY KEY,
    first_seen_s REAL NOT NULL,
    last_seen_s REAL NOT NULL,
    status TEXT,
    is_ok INTEGER,
    battery_level REAL,
    location TEXT,
    status_time_s REAL
)
"""
_COLUMNS = (
    "name", "first_seen_s", "last_seen_s", "status", "is_ok", "battery_level", "location",
    "status_time_s",
)
# Why: names come from topics clients send; bound the registry like every other table.
MAX_ROBOTS = 10000
MAX_NAME_CHARS = 128
# A full registry forgets this many of the robots seen longest ago at once (those no open
# connection speaks for), so the sort that finds them is paid once per that many names.
FORGET_AT_ONCE = MAX_ROBOTS // 10


@dataclass(frozen=True)
class RobotRecord:
    """What the server knows about one robot.

    Attributes:
        name: First path segment of its topics.
        first_seen_s / last_seen_s: Wall clock, seconds since the epoch.
        status / is_ok / battery_level / location: Last ``RobofleetStatus`` (``None`` if
            never received); battery_level is a fraction 0..1 as the robot reports it,
            ``None`` also when the robot reported it unknown (-1).
        status_time_s: Wall clock when that status arrived.
    """

    name: str
    first_seen_s: float
    last_seen_s: float
    status: str | None = None
    is_ok: bool | None = None
    battery_level: float | None = None
    location: str | None = None
    status_time_s: float | None = None


def robot_name(topic: str) -> str | None:
    """Return the first path segment of *topic* (``/husky1/scan`` -> ``husky1``), or ``None``."""
    # A topic with a single segment ("/status") names no robot.
    name, sep, rest = topic[1:].partition("/")
    if not topic.startswith("/") or not sep or not rest or not 0 < len(name) <= MAX_NAME_CHARS:
        return None
    return name


class RobotRegistry:
    """Robots, in memory with write-behind to SQLite.

    Args:
        path: SQLite file; ``None`` keeps the registry in memory only.
        offline_after_s: A robot with no frame for this long is offline.
        clock: Wall clock in seconds (injectable for tests).
    """

    def __init__(
        self,
        path: Path | None,
        offline_after_s: float,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.offline_after_s = offline_after_s
        self._clock = clock
        # Used from one thread at a time: the event loop, or the worker that runs
        # take_flush()'s job while the loop waits for it (RelayServer).
        try:
            self._db = sqlite3.connect(str(path) if path is not None else ":memory:",
                                       check_same_thread=False)
            self._db.execute(_SCHEMA)
            self._db.commit()
        except sqlite3.DatabaseError as exc:  # not a database, a directory, no permission
            raise ConfigError(f"{path}: field 'database' of the server config: cannot use "
                              f"it as the robot registry (SQLite): {exc}") from None
        self._robots: dict[str, RobotRecord] = {}
        self._last_seen: dict[str, float] = {}
        self._dirty: set[str] = set()
        self._live: dict[str, int] = {}  # robot -> open connections that speak for it
        self._forgotten: set[str] = set()  # to delete from SQLite at the next flush
        for row in self._db.execute(f"SELECT {', '.join(_COLUMNS)} FROM robots"):
            rec = RobotRecord(
                name=row[0], first_seen_s=row[1], last_seen_s=row[2], status=row[3],
                is_ok=None if row[4] is None else bool(row[4]),
                battery_level=known_battery(row[5]),
                location=row[6], status_time_s=row[7],
            )
            self._robots[rec.name] = rec
            self._last_seen[rec.name] = rec.last_seen_s
        self.dropped_names = 0
        self.forgotten_names = 0

    @property
    def db(self) -> sqlite3.Connection:
        """The SQLite connection (shared with the sessions table's ``SessionStore``)."""
        return self._db

    def seen(self, name: str) -> bool:
        """Note a frame from robot *name* now; return ``False`` if the registry is full."""
        now = self._clock()
        if name not in self._last_seen:
            if len(self._last_seen) >= MAX_ROBOTS and not self._make_room():
                self.dropped_names += 1
                return False
            self._robots[name] = RobotRecord(name, now, now)
            self._forgotten.discard(name)
        self._last_seen[name] = now
        self._dirty.add(name)
        return True

    def _make_room(self) -> bool:
        """Forget the :data:`FORGET_AT_ONCE` robots seen longest ago that no open
        connection speaks for; whether that made room. Why: a full registry refused every
        new name for good (and the table is kept across restarts), so a fleet whose robot
        names come and go (sims, replays, renamed robots) stopped showing new robots
        after its 10,000th name, while robots gone for months stayed listed."""
        idle = sorted((t, n) for n, t in self._last_seen.items() if n not in self._live)
        gone = idle[:FORGET_AT_ONCE]
        for _, name in gone:
            del self._robots[name], self._last_seen[name]
            self._dirty.discard(name)
            self._forgotten.add(name)
        self.forgotten_names += len(gone)
        if gone:
            log.info("robot registry full (%d robots): forgot the %d seen longest ago "
                     "(last seen %s to %s)", MAX_ROBOTS, len(gone), _when(gone[0][0]),
                     _when(gone[-1][0]))
        return len(self._last_seen) < MAX_ROBOTS

    def attach(self, name: str) -> None:
        """Note that one more open connection speaks for *name*."""
        self._live[name] = self._live.get(name, 0) + 1

    def detach(self, name: str) -> None:
        """Note that a connection speaking for *name* closed."""
        left = self._live.get(name, 0) - 1
        if left > 0:
            self._live[name] = left
        else:
            self._live.pop(name, None)

    def set_status(
        self, name: str, status: str, is_ok: bool, battery_level: float, location: str
    ) -> None:
        """Record a ``RobofleetStatus`` of robot *name* (call :meth:`seen` first); a
        *battery_level* that means unknown (-1) is recorded as ``None``."""
        rec = self._robots.get(name)
        if rec is None:
            return
        self._robots[name] = replace(
            rec, status=status, is_ok=is_ok, battery_level=known_battery(battery_level),
            location=location,
            status_time_s=self._clock(),
        )
        self._dirty.add(name)

    def online(self, name: str) -> bool:
        """Whether *name* has an open connection and sent a frame recently."""
        last = self._last_seen.get(name)
        return (
            last is not None
            and name in self._live
            and self._clock() - last < self.offline_after_s
        )

    def get(self, name: str) -> RobotRecord | None:
        """Return the record of *name* with its current last-seen time."""
        rec = self._robots.get(name)
        if rec is None:
            return None
        return replace(rec, last_seen_s=self._last_seen[name])

    def names(self) -> list[str]:
        """Return every known robot name, sorted."""
        return sorted(self._robots)

    def as_json(self, names: list[str] | None = None) -> list[dict[str, Any]]:
        """Return robots (all, or *names*) as JSON-ready dicts with ``online``."""
        out = []
        for name in self.names() if names is None else names:
            rec = self.get(name)
            if rec is not None:
                out.append({**asdict(rec), "online": self.online(name)})
        return out

    def flush(self) -> int:
        """Write changed robots to SQLite in one transaction (and delete forgotten ones,
        :meth:`seen`); return how many were written."""
        job = self.take_flush()
        return job() if job is not None else 0

    def take_flush(self) -> Callable[[], int] | None:
        """Take the changed robots now; return the job that writes them (one transaction,
        safe in a worker thread; returns how many), or ``None`` when nothing changed."""
        if not self._dirty and not self._forgotten:
            return None
        forgotten = [(name,) for name in self._forgotten]
        self._forgotten = set()
        rows = []
        for name in self._dirty:
            rec = self.get(name)
            if rec is not None:
                d = asdict(rec)
                rows.append(tuple(d[c] for c in _COLUMNS))
        self._dirty.clear()
        marks = ", ".join("?" for _ in _COLUMNS)
        db = self._db

        def job() -> int:
            with db:
                db.executemany("DELETE FROM robots WHERE name = ?", forgotten)
                db.executemany(
                    f"INSERT OR REPLACE INTO robots ({', '.join(_COLUMNS)}) VALUES ({marks})",
                    rows)
            return len(rows)

        return job

    def close(self) -> None:
        """Flush and close the database."""
        self.flush()
        self._db.close()


def _when(wall_s: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(wall_s))
