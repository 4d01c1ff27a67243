"""The robot registry shared by relay replicas through a JetStream KV bucket (issue 15).

Why: a robot's status and online state used to be known only on the replica it is
connected to, so the fleet overview of a viewer on another replica missed it, and a
replica's death took its robots' last status with it.

How: each replica keeps its own :class:`RobotRegistry` (every frame still touches memory
only) and, about once a second, writes what changed about *its* robots to the bucket,
one key per robot and replica (``<robot>.<replica>``): a replica never overwrites what
another one said, so a robot that moved from A to B is not marked offline by A's late
"detached" write. Every replica watches the whole bucket and merges: a robot is listed if
any replica knows it, its record is the one seen last, and it is online if its own
replica says it has a live connection and the robot's last frame is recent. A replica
that dies stops refreshing its entries, so its robots fall offline after
``robot_offline_after_s`` like a silent robot; a live entry is refreshed every third of
that time even when nothing else changed.

Per-frame cost: none (the writes are batched per tick). Single-process servers never
import this module.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from nats.aio.client import Client
from nats.js.kv import KeyValue

from fleetctl.server.cluster import kvloops
from fleetctl.server.cluster.config import ClusterConfig
from fleetctl.server.cluster.kvkeys import from_key_token, key_token
from fleetctl.server.fanout import MetricFamily
from fleetctl.server.registry import MAX_ROBOTS, RobotRecord, RobotRegistry

log = logging.getLogger("fleetctl.server.cluster")

# Concurrent KV puts per tick: enough to hide the round trip, few enough for a small NATS.
_PUTS_IN_FLIGHT = 64


def bucket_name(config: ClusterConfig) -> str:
    """The KV bucket of the robot registry: one per fleet (subject prefix)."""
    return f"{config.subject_prefix}_robots"


@dataclass(frozen=True)
class _Remote:
    """What another replica said about one robot."""

    record: RobotRecord
    live: bool


class SharedRegistry(RobotRegistry):
    """A replica's :class:`RobotRegistry` whose reads include the other replicas' robots.

    Writes (``seen``, ``attach``, ``set_status``...) are the local registry's; reads
    (``names``, ``get``, ``online``, so ``as_json``) merge the bucket's view.

    Args:
        path: The local SQLite file (``None``: memory), as for :class:`RobotRegistry`.
        offline_after_s: A robot with no frame for this long is offline.
        config: This replica's cluster section (its name, the fleet's prefix, the
            bucket's replicas).
        clock: Wall clock in seconds.
    """

    def __init__(self, path: Path | None, offline_after_s: float, config: ClusterConfig,
                 clock: Callable[[], float] = time.time) -> None:
        super().__init__(path, offline_after_s, clock)
        self.config = config
        self.refresh_s = max(0.05, min(1.0, offline_after_s / 3))
        self._remote: dict[str, dict[str, _Remote]] = {}  # robot -> replica -> entry
        self._said: dict[str, tuple[Any, ...]] = {}  # robot -> what we last wrote
        self._said_at: dict[str, float] = {}
        self._kv: KeyValue | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self.counters = {"puts": 0, "put_failures": 0, "received": 0, "malformed": 0}

    async def start(self, nc: Client) -> None:
        """Open (or create) the bucket, read it, then keep watching and writing.

        Raises:
            ClusterStartError: NATS has no JetStream, or the bucket cannot be made with
                ``state_replicas`` copies (names ``cluster.state_replicas``).
        """
        self._kv = await kvloops.open_bucket(nc, self.config, bucket_name(self.config),
                                             "the robot registry's")
        watcher = await self._kv.watchall()
        self._tasks = [asyncio.create_task(kvloops.watch(watcher, self.on_entry)),
                       asyncio.create_task(self._write_loop())]

    async def stop(self) -> None:
        """Write the last changes (best effort), stop watching."""
        await kvloops.stop(self.write_changes, self._tasks)
        self._tasks = []

    # -- merged reads ---------------------------------------------------------------------

    def names(self) -> list[str]:
        return sorted(set(super().names()) | set(self._remote))

    def get(self, name: str) -> RobotRecord | None:
        records = [r.record for r in self._remote.get(name, {}).values()]
        local = super().get(name)
        if local is not None:
            records.append(local)
        if not records:
            return None
        newest = max(records, key=lambda r: r.last_seen_s)
        with_status = [r for r in records if r.status_time_s is not None]
        status = max(with_status, key=lambda r: r.status_time_s or 0.0, default=newest)
        return replace(status, last_seen_s=newest.last_seen_s,
                       first_seen_s=min(r.first_seen_s for r in records))

    def online(self, name: str) -> bool:
        if super().online(name):
            return True
        now = self._clock()
        return any(r.live and now - r.record.last_seen_s < self.offline_after_s
                   for r in self._remote.get(name, {}).values())

    # -- writing --------------------------------------------------------------------------

    async def write_changes(self) -> int:
        """Write this replica's changed robots now; return how many were written."""
        kv = self._kv
        if kv is None:
            return 0
        now = self._clock()
        due: list[tuple[str, bytes, tuple[Any, ...]]] = []
        for name in super().names():
            rec = super().get(name)
            if rec is None:
                continue
            live = name in self._live
            said = (live, rec.status, rec.is_ok, rec.battery_level, rec.location,
                    rec.status_time_s)
            old = self._said.get(name)
            stale = live and now - self._said_at.get(name, -math.inf) >= self.refresh_s
            if old == said and not stale:
                continue
            value = json.dumps({**asdict(rec), "live": live}, separators=(",", ":"))
            due.append((name, value.encode(), said))
        written = 0
        for start in range(0, len(due), _PUTS_IN_FLIGHT):
            chunk = due[start:start + _PUTS_IN_FLIGHT]
            results = await asyncio.gather(
                *(kv.put(f"{key_token(n)}.{self.config.name}", v) for n, v, _ in chunk),
                return_exceptions=True)
            for (name, _, said), result in zip(chunk, results, strict=True):
                if isinstance(result, BaseException):
                    self.counters["put_failures"] += 1
                    continue  # not marked said: retried next tick
                self._said[name] = said
                self._said_at[name] = now
                written += 1
        self.counters["puts"] += written
        return written

    async def _write_loop(self) -> None:
        async def tick() -> None:
            await asyncio.sleep(self.refresh_s)  # a tick, not synchronization

        await kvloops.write_forever(tick, self.write_changes, self.counters,
                                    "shared robot registry", self.refresh_s)

    # -- watching -------------------------------------------------------------------------

    def on_entry(self, key: str, value: bytes | None, operation: str | None) -> None:
        """One bucket entry (from the watch): note another replica's view of a robot."""
        robot_token, _, replica = key.rpartition(".")
        if replica == self.config.name:
            return  # our own write, already known locally
        try:
            name = from_key_token(robot_token)
        except (ValueError, UnicodeDecodeError):
            self.counters["malformed"] += 1
            return
        if operation in ("DEL", "PURGE") or not value:
            entries = self._remote.get(name, {})
            entries.pop(replica, None)
            if not entries:
                self._remote.pop(name, None)
            return
        remote = _parse(name, value)
        if remote is None:
            self.counters["malformed"] += 1
            return
        if name not in self._remote and len(self._remote) >= MAX_ROBOTS:
            self.dropped_names += 1
            return
        self._remote.setdefault(name, {})[replica] = remote
        self.counters["received"] += 1

    def metric_families(self) -> Iterable[MetricFamily]:
        return [("fleetctl_cluster_registry_total", "counter",
                 "Shared robot registry: KV writes, failed writes, entries received from "
                 "other replicas, malformed entries.", "event",
                 {k: float(v) for k, v in self.counters.items()})]


def _parse(name: str, value: bytes) -> _Remote | None:
    """A bucket value, checked field by field (another replica's or anyone's bytes)."""
    try:
        data = json.loads(value)
    except ValueError:
        return None
    if not isinstance(data, dict) or data.get("name") != name:
        return None

    def num(key: str, optional: bool = False) -> float | None:
        v = data.get(key)
        if v is None and optional:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(key)
        return float(v)

    def text(key: str) -> str | None:
        v = data.get(key)
        if v is not None and not isinstance(v, str):
            raise ValueError(key)
        return v

    try:
        first, last = num("first_seen_s"), num("last_seen_s")
        assert first is not None and last is not None
        is_ok = data.get("is_ok")
        live = data.get("live")
        if (is_ok is not None and not isinstance(is_ok, bool)) or not isinstance(live, bool):
            return None
        record = RobotRecord(name=name, first_seen_s=first, last_seen_s=last,
                             status=text("status"), is_ok=is_ok,
                             battery_level=num("battery_level", True),
                             location=text("location"),
                             status_time_s=num("status_time_s", True))
    except ValueError:
        return None
    return _Remote(record, live)
