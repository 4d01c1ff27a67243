"""What every piece of replica state kept in JetStream KV does (the shared robot
registry, the shared latched messages): open its bucket, watch it, write this replica's
changes with failures counted and logged once per outage, and stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from nats.aio.client import Client
from nats.js.errors import Error as JetStreamError
from nats.js.errors import NoStreamResponseError, ServiceUnavailableError
from nats.js.kv import KeyValue

from fleetctl.server.cluster.config import ClusterConfig, ClusterStartError

log = logging.getLogger("fleetctl.server.cluster")

T = TypeVar("T")
# How long a replica's start waits for JetStream to answer (each try: nats-py's 5 s).
ELECTION_WAIT_S = 20.0
# What a JetStream request gets while the stream it writes to has no leader yet.
_ELECTING = (NoStreamResponseError, ServiceUnavailableError)

OnEntry = Callable[[str, bytes | None, str | None], None]
"""``(key, value, operation)`` of one bucket entry."""


async def open_bucket(nc: Client, config: ClusterConfig, name: str, what: str,
                      **options: Any) -> KeyValue:
    """Open (or create) KV bucket *name* with ``state_replicas`` copies, history 1.

    Raises:
        ClusterStartError: NATS has no JetStream, or the bucket cannot be made with that
            many copies (names ``cluster.state_replicas``; *what* says whose bucket).
    """
    try:
        return await while_electing(lambda: nc.jetstream().create_key_value(
            bucket=name, history=1, replicas=config.state_replicas, **options))
    except (TimeoutError, JetStreamError) as exc:
        raise ClusterStartError(
            f"field 'cluster.state_replicas': cannot open {what} JetStream KV bucket "
            f"{name!r} with {config.state_replicas} replica(s): {exc!r} (is JetStream "
            "enabled on every NATS node, and are there that many?)") from exc


async def while_electing(call: Callable[[], Awaitable[T]]) -> T:
    """*call* (a JetStream API request), retried on timeouts for up to
    :data:`ELECTION_WAIT_S`: a NATS cluster that has just started (``fleetctl up`` starts
    it with the replicas) answers JetStream requests only once its meta leader is elected
    and settled, which takes a few seconds."""
    deadline = asyncio.get_running_loop().time() + ELECTION_WAIT_S
    while True:
        try:
            return await call()
        except TimeoutError:
            if asyncio.get_running_loop().time() >= deadline:
                raise
            log.info("JetStream does not answer yet (leader election?): retrying")


def raise_if_cancelled() -> None:
    """Re-raise a cancellation a NATS call turned into an error: in Python 3.11
    ``asyncio.wait_for`` (under every nats-py request) can lose a cancellation that comes
    as its answer does, and a loop that catches the error would then never stop.

    Raises:
        asyncio.CancelledError: The current task is being cancelled.
    """
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError


async def stop(last_write: Callable[[], Awaitable[int]],
               tasks: list[asyncio.Task[None]]) -> None:
    """Write the last changes (best effort, 2 s at most), then cancel *tasks* and wait
    for them (2 s at most: a task that ignores its cancellation is left behind, logged)."""
    with contextlib.suppress(Exception):
        await asyncio.wait_for(last_write(), 2.0)
    for task in tasks:
        task.cancel()
    if tasks:
        _, pending = await asyncio.wait(tasks, timeout=2.0)
        for task in pending:
            log.warning("task %s (%s) did not stop within 2 s of its cancellation",
                        task.get_name(), task.get_coro())


async def watch(watcher: KeyValue.KeyWatcher, on_entry: OnEntry) -> None:
    """Hand every entry the watch yields to *on_entry* (the bucket's latest values at
    start, then every change), until cancelled."""
    async for entry in watcher:
        if entry is None:  # the end of what the bucket held at start
            continue
        on_entry(entry.key, entry.value, entry.operation)


async def write_forever(tick: Callable[[], Awaitable[None]], write: Callable[[], Awaitable[int]],
                        counters: dict[str, int], what: str, retry_s: float) -> None:
    """Wait for *tick*, call *write*, forever. Failures count in ``put_failures`` (an
    exception from *write* too); one WARNING when writes start failing, one INFO when
    they work again, naming *what*.

    A bucket created a moment ago in a NATS cluster that has just started has no stream
    leader yet: its first writes fail with "no responders" or a 503 for a second or two.
    Within :data:`ELECTION_WAIT_S` of the start such a failure is an INFO, not a WARNING
    (it is how every ``fleetctl up --replicas`` begins); any other failure, or that one
    later, warns."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    failing = warned = False
    while True:
        raise_if_cancelled()  # a cancellation a NATS request swallowed
        await tick()
        before = counters["put_failures"]
        error: Exception | None = None
        try:
            await write()
        except Exception as exc:
            raise_if_cancelled()
            counters["put_failures"] += 1
            error = exc
        if counters["put_failures"] == before:
            if failing:
                log.info("%s: writing again", what)
            failing = warned = False
            continue
        if isinstance(error, _ELECTING) and loop.time() - start < ELECTION_WAIT_S:
            if not failing:
                log.info("%s: not written yet: %r (JetStream electing its leaders after a "
                         "start?): retrying every %.2f s", what, error, retry_s)
        elif not warned:
            if error is not None:
                log.warning("cannot write the %s: %r", what, error)
            log.warning("%s: writes failing (NATS away?); retrying every %.2f s", what,
                        retry_s)
            warned = True
        failing = True
