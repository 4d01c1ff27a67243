"""Write relayed frames in the read that brought them, not in a later loop round.

Each connection has a writer task that pops its outbound queue as fast as the socket drains
(:meth:`fleetctl.server.app.RelayServer._write_loop`). When a sender's frame lands in an
empty queue, the queue wakes that task; it runs in the event loop's *next* round, after
whatever else is ready, and only then writes. On loopback (``benchmarks/peer_latency.py``,
packet times read off ``lo``) that hop was 0.15-0.2 ms of the relay's 0.5 ms per message.

While a connection's received bytes are being handled (between :meth:`WriteThrough.begin`
and :meth:`WriteThrough.end`), wakes are collected instead; when the handling ends, every
woken connection whose writer is idle
and whose transport is below its write limit gets its queue written right there, one batch
each (the same batch the task would have written: one read of many frames still costs one
write per receiver). A connection that cannot be written at once (its writer busy or
waiting for the socket, more queued than one batch) is woken as before. Outside a
collection (a NATS frame, a timer, the reader task) a wake is the plain wake.

The writer task stays the only one that waits for a slow socket; this only saves the round
when there is nothing to wait for.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable


class ConnectionWriter:
    """One connection's cue for its writer task, and its write-through.

    Args:
        through: The loop's :class:`WriteThrough`.

    Attributes:
        write_now: Writes one batch of the queue synchronously if it can; returns True
            when the queue is empty afterwards (False: the task must run). Set once the
            connection's peer exists; None: never written through.
    """

    __slots__ = ("_through", "collected", "event", "idle", "write_now")

    def __init__(self, through: WriteThrough) -> None:
        self.event = asyncio.Event()
        self.idle = False  # the writer task waits on event (so it is not mid-write)
        self.collected = False
        self.write_now: Callable[[], bool] | None = None
        self._through = through

    def wake(self) -> None:
        """The queue went from empty to non-empty."""
        through = self._through
        if through.collecting and self.idle and self.write_now is not None:
            if not self.collected:
                self.collected = True
                through.pending.append(self)
            return
        self.event.set()

    def write_through(self) -> None:
        """Write now, or wake the task when that is not possible."""
        self.collected = False
        write_now = self.write_now
        if not (self.idle and write_now is not None and write_now()):
            self.event.set()


class WriteThrough:
    """The loop-wide collection of wakes (see the module docstring)."""

    __slots__ = ("collecting", "pending", "written")

    def __init__(self) -> None:
        self.collecting = False
        self.pending: list[ConnectionWriter] = []
        self.written = 0  # batches written through (a test's and a profile's view)

    def begin(self) -> bool:
        """Start collecting; False when a collection is already open (nested reads)."""
        if self.collecting:
            return False
        self.collecting = True
        return True

    def end(self) -> None:
        """Stop collecting and write (or wake) every collected connection."""
        self.collecting = False
        pending = self.pending
        if not pending:
            return
        self.pending = []
        for writer in pending:
            writer.write_through()
