"""Which subjects the other replicas want: a replica publishes a frame to NATS only if one
of them has a subscriber for it (issue 15; docs/scaling.md, "Publishing where wanted").

Why: NATS drops a message nobody subscribed to, but only after the publishing replica has
paid for it (nats-py's per-message path, ~1.7 us, a third of a replica's cost per frame)
and sent it to its NATS node. A fleet of 1,000 robots whose viewers watch a few of them
would push every frame of every robot into NATS.

How: every replica writes the subjects it holds on core NATS (its interest, see
:mod:`~fleetctl.server.cluster.interest`) to the KV bucket ``<prefix>_interest``, one
key per replica, after it has subscribed to them, and rewrites it every
:data:`REFRESH_S`. Every replica watches the bucket and publishes a frame only when a
subject some other replica wants covers the frame's subject (memoized per subject until
the next change).

Fail-safe: when in doubt, publish (today's behaviour). Before the watch has delivered the
bucket's contents, and while this replica's own rewrites stop coming back through the
watch (JetStream away), every frame is published. A value that is not a list of subjects
counts as wanting everything. A replica that died without deleting its key is forgotten
:data:`TTL_S` after its last rewrite.

The price: a viewer's first frames from another replica wait for its replica's write to
reach the publisher (a KV write and a watch delivery, about a millisecond), as they
already waited for the core subscription to cross NATS's routes.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import Callable, Iterable

from nats.aio.client import Client
from nats.js.kv import KeyValue

from fleetctl.server.cluster import kvloops
from fleetctl.server.cluster.config import ClusterConfig
from fleetctl.server.cluster.kvkeys import from_key_token, key_token
from fleetctl.server.cluster.subjects import MAX_SUBJECT_BYTES, covered, subject_matches
from fleetctl.server.fanout import MetricFamily

log = logging.getLogger("fleetctl.server.cluster")

# A replica rewrites its key this often; one not rewritten for TTL_S is gone.
REFRESH_S = 10.0
TTL_S = 30.0
RETRY_S = 1.0
# A replica's list longer than this (JSON bytes) is written as "everything" instead
# (NATS's default max_payload is 1 MiB).
MAX_VALUE_BYTES = 256 * 1024
_MAX_MEMO = 65536


def bucket_name(config: ClusterConfig) -> str:
    return f"{config.subject_prefix}_interest"


def encode_subjects(prefix: str, subjects: Iterable[str]) -> bytes:
    """A replica's value: its subjects as JSON, or ``<prefix>.>`` if that is too long."""
    value = json.dumps({"subjects": sorted(subjects)}, separators=(",", ":")).encode()
    if len(value) > MAX_VALUE_BYTES:
        value = json.dumps({"subjects": [f"{prefix}.>"]}).encode()
    return value


def decode_subjects(prefix: str, value: bytes) -> frozenset[str]:
    """A replica's subjects.

    Raises:
        ValueError: Not a JSON object with a list of subjects of this fleet.
    """
    try:
        subjects = json.loads(value)["subjects"]
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"not an interest value: {exc}") from None
    if not isinstance(subjects, list):
        raise ValueError("'subjects' is not a list")
    for subject in subjects:
        if (not isinstance(subject, str) or len(subject) > MAX_SUBJECT_BYTES
                or not subject.startswith(prefix + ".") or " " in subject
                or "" in subject.split(".")):
            raise ValueError(f"not a subject of this fleet: {subject!r}")
    return frozenset(subjects)


class RemoteInterest:
    """This replica's announcement of its interest, and its view of the others'.

    Args:
        config: This replica's cluster section.
        clock: Monotonic seconds (when an entry was last seen).
    """

    def __init__(self, config: ClusterConfig,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self._clock = clock
        self._own_key = key_token(config.name)
        self._others: dict[str, tuple[frozenset[str], float]] = {}  # replica -> subjects, seen
        self._own_seen: float | None = None  # our own last write, as the watch returned it
        self._exact: set[str] = set()
        self._wide: set[str] = set()  # X of every X.>
        self._odd: list[str] = []  # other wildcards (never written by a replica of ours)
        self._memo: dict[str, bool] = {}
        self.synced = False  # the watch delivered the bucket's contents
        self._was_trusted = False
        self._wanted: frozenset[str] | None = None
        self._written: frozenset[str] | None = None
        self._written_s = 0.0
        self._wake = asyncio.Event()
        self._kv: KeyValue | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self.counters = {"puts": 0, "put_failures": 0, "received": 0, "malformed": 0,
                         "expired": 0}

    async def start(self, nc: Client) -> None:
        """Open (or create) the bucket, then watch it and write this replica's key.

        Raises:
            ClusterStartError: The bucket cannot be made (names ``cluster.state_replicas``).
        """
        self._kv = await kvloops.open_bucket(nc, self.config, bucket_name(self.config),
                                             "the replicas' interest", ttl=TTL_S)
        watcher = await self._kv.watchall()
        self._tasks = [asyncio.create_task(self._watch(watcher)),
                       asyncio.create_task(self._write_loop())]

    async def stop(self) -> None:
        """Delete this replica's key (best effort): the others stop publishing to it."""
        await kvloops.stop(self._delete_own, self._tasks)
        self._tasks = []

    # -- the publisher's question -------------------------------------------------------

    def wants(self, subject: str) -> bool:
        """Whether another replica wants frames on *subject* (a topic's subject, no
        wildcards); ``True`` while in doubt."""
        hit = self._memo.get(subject)
        if hit is None:
            hit = self._match(subject) or not self.trusted()
            if len(self._memo) >= _MAX_MEMO:
                self._memo.clear()
            self._memo[subject] = hit
        return hit

    def known(self) -> dict[str, frozenset[str]]:
        """The other replicas' subjects, by replica name."""
        return {replica: subjects for replica, (subjects, _) in self._others.items()}

    def trusted(self) -> bool:
        """The view is complete and current: the bucket was read, and this replica's own
        last write came back through the watch within :data:`TTL_S`."""
        seen = self._own_seen
        return self.synced and seen is not None and self._clock() - seen <= TTL_S

    def _match(self, subject: str) -> bool:
        if subject in self._exact or covered(subject, self._wide):
            return True
        return any(subject_matches(subject, pattern) for pattern in self._odd)

    # -- this replica's interest --------------------------------------------------------

    def announce(self, wanted: frozenset[str]) -> None:
        """This replica now holds core subscriptions on *wanted*: write it."""
        self._wanted = wanted
        self._wake.set()

    async def _write_loop(self) -> None:
        async def tick() -> None:
            # A write still due (a failed one) is tried again after RETRY_S.
            wait_s = RETRY_S if self._due() else REFRESH_S / 2
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), wait_s)
            self._wake.clear()
            self._expire()

        await kvloops.write_forever(tick, self.write_due, self.counters,
                                    "replicas' interest", RETRY_S)

    def _due(self) -> bool:
        """This replica's subjects changed since the last write, or it is due for a
        refresh."""
        return (self._wanted or frozenset()) != self._written \
            or self._clock() - self._written_s >= REFRESH_S

    async def write_due(self) -> int:
        """Write this replica's subjects if :meth:`_due` (a failure raises: the write
        loop counts and logs it)."""
        kv, wanted = self._kv, self._wanted or frozenset()
        if kv is None or not self._due():
            return 0
        await kv.put(self._own_key, encode_subjects(self.config.subject_prefix, wanted))
        self.counters["puts"] += 1
        self._written, self._written_s = wanted, self._clock()
        return 1

    async def _delete_own(self) -> int:
        if self._kv is None:
            return 0
        await self._kv.delete(self._own_key)
        return 1

    # -- the other replicas' interest ---------------------------------------------------

    async def _watch(self, watcher: KeyValue.KeyWatcher) -> None:
        async for entry in watcher:
            if entry is None:
                self.synced = True
                self._changed()
                continue
            self.on_entry(entry.key, entry.value, entry.operation)

    def on_entry(self, key: str, value: bytes | None, operation: str | None) -> None:
        """One bucket entry: a replica's subjects, or its key deleted."""
        self.counters["received"] += 1
        now = self._clock()
        if key == self._own_key:
            self._own_seen = None if operation in ("DEL", "PURGE") else now
            self._forget_answers()  # trust may have changed
            return
        try:
            replica = from_key_token(key)
        except (ValueError, UnicodeDecodeError):
            self.counters["malformed"] += 1
            replica = key
        if operation in ("DEL", "PURGE") or not value:
            self._others.pop(replica, None)
        else:
            try:
                subjects = decode_subjects(self.config.subject_prefix, value)
            except ValueError as exc:
                self.counters["malformed"] += 1
                log.warning("replica %s: replica %r's interest is malformed (%s): "
                            "publishing everything to it", self.config.name, replica, exc)
                subjects = frozenset({f"{self.config.subject_prefix}.>"})
            self._others[replica] = (subjects, now)
        self._changed()

    def _expire(self) -> None:
        """Forget replicas not heard of for :data:`TTL_S` (died without deleting their
        key) while this replica's own writes still come back (else the watch, not they,
        is what stopped)."""
        now = self._clock()
        if self.trusted() != self._was_trusted:  # the memo assumed the other state
            self._forget_answers()
        if not self._was_trusted:
            return
        gone = [r for r, (_, seen) in self._others.items() if now - seen > TTL_S]
        for replica in gone:
            del self._others[replica]
            self.counters["expired"] += 1
            log.info("replica %s: replica %r's interest expired (no refresh for %.0f s)",
                     self.config.name, replica, TTL_S)
        if gone:
            self._changed()

    def _changed(self) -> None:
        every = set().union(*(s for s, _ in self._others.values()))
        self._exact = {s for s in every if "*" not in s and ">" not in s}
        self._wide = {s[:-2] for s in every if s.endswith(".>") and "*" not in s[:-2]
                      and ">" not in s[:-2]}
        self._odd = [s for s in every if s not in self._exact
                     and not (s.endswith(".>") and s[:-2] in self._wide)]
        self._forget_answers()

    def _forget_answers(self) -> None:
        """Clear the memo; the answers from here on assume today's trust."""
        self._memo.clear()
        self._was_trusted = self.trusted()

    def metric_families(self) -> Iterable[MetricFamily]:
        return [("fleetctl_cluster_interest_total", "counter",
                 "The replicas' interest bucket: this replica's writes and failures, "
                 "entries received, malformed, expired.", "event",
                 {k: float(v) for k, v in self.counters.items()}),
                ("fleetctl_cluster_interest_replicas", "gauge",
                 "Other replicas whose interest this replica knows.", "",
                 {"": float(len(self._others))})]
