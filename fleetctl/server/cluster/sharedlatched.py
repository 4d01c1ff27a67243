"""Latched messages shared by relay replicas through a JetStream KV bucket (issue 15).

Why: a latched message (a map, ``/tf_static``, a robot description) is published once. A
viewer on replica B that subscribes after the robot on replica A sent its map must get
it first, as it would from one server; and a replica started later (or restarted) must
have it too, though it had no interest in the topic when the frame went by on NATS.

How: every replica keeps its own :class:`~fleetctl.server.latched.LatchedStore` (serving a
new subscription touches memory only). When a *local* sender's message becomes the one
kept for (sender, topic), this module writes it to the bucket ``<prefix>_latched`` under
``<sender>.<topic>`` (each identity name and the topic as a KV token, see
:func:`~fleetctl.server.cluster.kvkeys.key_token`; names joined with ``/``), the frames as
they came on the wire. When a local sender's message may no longer be served (its newer
message was too big to keep, an auth reload revoked it), the key is deleted. Every
replica watches the bucket and puts the other replicas' messages into its own store
(:meth:`LatchedStore.put_remote`), after checking that the sender may still send on the
topic under *this* replica's auth map; a delete drops what another replica had shared.

Value: ``FLL1``, one byte of replica-name length, the replica's name (so a replica skips
its own writes coming back), a u32 frame count, then each frame as a u32 length and its
bytes (little endian). A message whose value would pass NATS's ``max_payload`` is kept
locally only and counted ``too_big``; the older shared one is deleted with it, so no
replica serves a message older than the sender's newest.

Bounds: the bucket holds at most ``latched_bytes`` x :data:`BUCKET_BYTES_FACTOR` (every
replica's senders together); writes past it fail and are counted. Writes waiting for NATS
are coalesced per key (only the newest message of a key is written), at most
:data:`MAX_DUE` keys.

Per-frame cost: none on the relay's hot path; one KV write per latched message stored.
Single-process servers never import this module.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
from collections.abc import Callable, Iterable

from nats.aio.client import Client
from nats.js.kv import KeyValue

from fleetctl.server.cluster import kvloops
from fleetctl.server.cluster.config import ClusterConfig
from fleetctl.server.cluster.kvkeys import from_key_token, key_token
from fleetctl.server.fanout import MetricFamily
from fleetctl.server.latched import LatchedStore, SenderKey

log = logging.getLogger("fleetctl.server.cluster")

MAGIC = b"FLL1"
_U32 = struct.Struct("<I")
# The bucket is shared by every replica's senders; each store holds latched_bytes.
BUCKET_BYTES_FACTOR = 4
# Keys waiting to be written while NATS is slow or away (a store holds 4096 keys).
MAX_DUE = 8192
# Room left in a NATS message for the KV put's subject and headers.
_PAYLOAD_MARGIN = 4096
_PUTS_IN_FLIGHT = 32
RETRY_S = 1.0

Allowed = Callable[[SenderKey, str], bool]
"""Whether *sender* may (still) send on *topic* under this replica's auth map."""


def bucket_name(config: ClusterConfig) -> str:
    """The KV bucket of the latched messages: one per fleet (subject prefix)."""
    return f"{config.subject_prefix}_latched"


def entry_key(sender: SenderKey, topic: str) -> str:
    """The KV key of (*sender*, *topic*)."""
    return "/".join(key_token(n) for n in sender) + "." + key_token(topic)


def parse_key(key: str) -> tuple[SenderKey, str]:
    """The inverse of :func:`entry_key`.

    Raises:
        ValueError: Not a key :func:`entry_key` makes.
    """
    names, dot, topic = key.partition(".")
    if not dot or not names or not topic or "." in topic:
        raise ValueError(f"bad latched key {key!r}")
    return tuple(from_key_token(n) for n in names.split("/")), from_key_token(topic)


def encode_value(replica: str, frames: list[bytes]) -> bytes:
    """The bucket value of one message written by *replica*."""
    name = replica.encode()
    parts = [MAGIC, bytes([len(name)]), name, _U32.pack(len(frames))]
    for frame in frames:
        parts += (_U32.pack(len(frame)), frame)
    return b"".join(parts)


def decode_value(value: bytes, max_bytes: int) -> tuple[str, list[bytes]]:
    """``(replica, frames)`` of a bucket value, checked (anyone with bucket access may
    have written it).

    Raises:
        ValueError: Not a value :func:`encode_value` makes, or frames over *max_bytes*.
    """
    view = memoryview(value)
    if bytes(view[:4]) != MAGIC or len(view) < 5:
        raise ValueError("no FLL1 header")
    n = view[4]
    pos = 5 + n
    if len(view) < pos + 4:
        raise ValueError("truncated header")
    replica = bytes(view[5:pos]).decode()
    (count,) = _U32.unpack_from(view, pos)
    pos += 4
    frames: list[bytes] = []
    total = 0
    for _ in range(count):
        if len(view) < pos + 4:
            raise ValueError("truncated frame length")
        (length,) = _U32.unpack_from(view, pos)
        pos += 4
        total += length
        if pos + length > len(view) or total > max_bytes:
            raise ValueError("frame past the value's end or over the bound")
        frames.append(bytes(view[pos:pos + length]))
        pos += length
    if pos != len(view) or not frames:
        raise ValueError("trailing bytes or no frame")
    return replica, frames


class SharedLatched:
    """Writes local senders' latched messages to the bucket and mirrors the others'.

    Args:
        config: This replica's cluster section.
        store: The replica's latched store (its listener becomes this object).
        allowed: Whether a sender may still send on a topic here (checked before a
            message from another replica is kept).
    """

    def __init__(self, config: ClusterConfig, store: LatchedStore, allowed: Allowed) -> None:
        self.config = config
        self.store = store
        self.allowed = allowed
        self._due: dict[tuple[SenderKey, str], list[bytes] | None] = {}  # None: delete
        self._wake = asyncio.Event()
        self._kv: KeyValue | None = None
        self._max_value = 0
        self._tasks: list[asyncio.Task[None]] = []
        self.counters = {"puts": 0, "deletes": 0, "put_failures": 0, "received": 0,
                         "forgotten": 0, "refused": 0, "malformed": 0, "too_big": 0,
                         "queue_full": 0}
        store.listener = self

    async def start(self, nc: Client) -> None:
        """Open (or create) the bucket, load what it holds, then keep watching and
        writing.

        Raises:
            ClusterStartError: NATS has no JetStream, or the bucket cannot be made with
                ``state_replicas`` copies (names ``cluster.state_replicas``).
        """
        self._max_value = max(0, nc.max_payload - _PAYLOAD_MARGIN)
        self._kv = await kvloops.open_bucket(
            nc, self.config, bucket_name(self.config), "the latched messages'",
            max_bytes=BUCKET_BYTES_FACTOR * self.store.max_bytes)
        watcher = await self._kv.watchall()
        self._tasks = [asyncio.create_task(kvloops.watch(watcher, self.on_entry)),
                       asyncio.create_task(self._write_loop())]
        self._wake.set()  # what local senders stored before NATS was up

    async def stop(self) -> None:
        """Write what is due (best effort), stop watching."""
        await kvloops.stop(self.write_due, self._tasks)
        self._tasks = []

    # -- LatchedListener (the store, on the event loop) ---------------------------------

    def stored(self, sender: SenderKey, topic: str, frames: list[bytes]) -> None:
        self._queue((sender, topic), frames)

    def forgotten(self, sender: SenderKey, topic: str) -> None:
        self._queue((sender, topic), None)

    def _queue(self, key: tuple[SenderKey, str], frames: list[bytes] | None) -> None:
        if key not in self._due and len(self._due) >= MAX_DUE:
            self.counters["queue_full"] += 1
            return
        self._due[key] = frames
        self._wake.set()

    # -- writing --------------------------------------------------------------------------

    async def write_due(self) -> int:
        """Write (or delete) every due key now; return how many succeeded. Failed ones
        stay due unless a newer change of the same key came meanwhile."""
        kv = self._kv
        if kv is None or not self._due:
            return 0
        due, self._due = self._due, {}
        done = 0
        items = list(due.items())
        for start in range(0, len(items), _PUTS_IN_FLIGHT):
            chunk = items[start:start + _PUTS_IN_FLIGHT]
            results = await asyncio.gather(*(self._write_one(kv, k, f) for k, f in chunk),
                                           return_exceptions=True)
            for (key, frames), result in zip(chunk, results, strict=True):
                if isinstance(result, BaseException):
                    self.counters["put_failures"] += 1
                    if key not in self._due and len(self._due) < MAX_DUE:
                        self._due[key] = frames  # retried on the next tick
                else:
                    done += 1
        return done

    async def _write_one(self, kv: KeyValue, key: tuple[SenderKey, str],
                         frames: list[bytes] | None) -> None:
        name = entry_key(*key)
        if frames is not None:
            value = encode_value(self.config.name, frames)
            if len(value) <= self._max_value:
                await kv.put(name, value)
                self.counters["puts"] += 1
                return
            self.counters["too_big"] += 1
            log.warning("latched message on %r (%d bytes) is past NATS's max_payload: kept "
                        "on this replica only", key[1], len(value))
        await kv.delete(name)  # never leave an older message than the sender's newest
        self.counters["deletes"] += 1

    async def _write_loop(self) -> None:
        async def tick() -> None:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), RETRY_S)  # or retry after this
            self._wake.clear()

        await kvloops.write_forever(tick, self.write_due, self.counters,
                                    "shared latched messages", RETRY_S)

    # -- watching -------------------------------------------------------------------------

    def on_entry(self, key: str, value: bytes | None, operation: str | None) -> None:
        """One bucket entry (from the watch): keep or forget another replica's message."""
        try:
            sender, topic = parse_key(key)
        except (ValueError, UnicodeDecodeError):
            self.counters["malformed"] += 1
            return
        if operation in ("DEL", "PURGE") or not value:
            if self.store.forget_remote(sender, topic):
                self.counters["forgotten"] += 1
            return
        try:
            replica, frames = decode_value(value, self.store.max_message_bytes)
        except (ValueError, UnicodeDecodeError):
            self.counters["malformed"] += 1
            return
        if replica == self.config.name:
            return  # our own write, already in the store
        if not self.allowed(sender, topic):
            self.counters["refused"] += 1
            return
        if self.store.put_remote(sender, topic, frames):
            self.counters["received"] += 1

    def metric_families(self) -> Iterable[MetricFamily]:
        return [("fleetctl_cluster_latched_total", "counter",
                 "Shared latched messages: KV writes and deletes, failed writes, messages "
                 "received from other replicas, forgotten on their delete, refused by this "
                 "replica's auth map, malformed, too big for NATS, not queued (too many "
                 "due).", "event", {k: float(v) for k, v in self.counters.items()})]
