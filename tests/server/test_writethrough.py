"""Write-through of relayed frames: the collection (unit) and a real relay (integration)."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection

from fleetctl.batched_connection import BatchedWritesConnection
from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerLimits
from fleetctl.server.connection import RelayConnection
from fleetctl.server.writethrough import ConnectionWriter, WriteThrough
from tests.server.conftest import BOB_TOKEN, client, next_binary, subscribe, wait_for
from tests.support import decode_text, string_frame


class FakeQueue:
    """What write_now sees: how many batches are queued, and whether it may write."""

    def __init__(self, batches: int = 1, writable: bool = True) -> None:
        self.batches = batches
        self.writable = writable
        self.writes = 0

    def write_now(self) -> bool:
        if not self.writable:
            return False
        self.writes += 1
        self.batches -= 1
        return self.batches == 0


def writer(through: WriteThrough, queue: FakeQueue, *, idle: bool = True) -> ConnectionWriter:
    w = ConnectionWriter(through)
    w.write_now = queue.write_now
    w.idle = idle
    return w


async def test_a_wake_outside_a_collection_wakes_the_task() -> None:
    through, queue = WriteThrough(), FakeQueue()
    w = writer(through, queue)
    w.wake()
    assert w.event.is_set() and queue.writes == 0


async def test_wakes_in_a_collection_are_written_once_at_its_end() -> None:
    through = WriteThrough()
    a, b = FakeQueue(), FakeQueue()
    wa, wb = writer(through, a), writer(through, b)
    assert through.begin()
    assert not through.begin()  # nested: the outer collection ends it
    wa.wake()
    wa.wake()  # a second wake of the same connection is one write
    wb.wake()
    assert (a.writes, b.writes) == (0, 0)
    through.end()
    assert (a.writes, b.writes) == (1, 1)
    assert not wa.event.is_set() and not wb.event.is_set()
    assert not through.collecting and through.pending == []


async def test_a_connection_that_cannot_be_written_now_wakes_its_task() -> None:
    through = WriteThrough()
    busy = writer(through, FakeQueue(), idle=False)  # its task is mid-write
    full = FakeQueue(writable=False)  # its transport is above the write limit
    blocked = writer(through, full)
    more = FakeQueue(batches=2)  # more than one batch queued
    long = writer(through, more)
    plain = ConnectionWriter(through)  # no write_now (a Foxglove connection's)
    plain.idle = True
    through.begin()
    for w in (busy, blocked, long, plain):
        w.wake()
    through.end()
    assert busy.event.is_set() and blocked.event.is_set() and plain.event.is_set()
    assert full.writes == 0
    assert more.writes == 1 and long.event.is_set()  # one batch, then the task goes on


class BatchedClient(BatchedWritesConnection, ClientConnection):
    """A client that sends a batch and a ping in one write, as the robot link does."""


async def test_relayed_frames_are_written_in_the_read_and_before_the_senders_pong(
    server: RelayServer, monkeypatch: pytest.MonkeyPatch,
) -> None:
    written: list[tuple[int, int]] = []  # (id of the server connection, opcode), in order
    flush: Callable[..., Any] = BatchedWritesConnection._flush

    def recording_flush(self: BatchedWritesConnection, pending: list[bytes]) -> None:
        if isinstance(self, RelayConnection):  # the server's writes, not the robot's
            written.extend((id(self), chunk[0] & 0x0F) for chunk in pending if chunk)
        flush(self, pending)

    async with client(server, token=BOB_TOKEN) as viewer, \
            client(server, source="127.0.0.2", create_connection=BatchedClient) as robot:
        await subscribe(viewer, "/husky1/.*")
        assert isinstance(robot, BatchedClient)
        monkeypatch.setattr(BatchedWritesConnection, "_flush", recording_flush)
        before = server.write_through.written
        pong = await robot.send_frames([string_frame("/husky1/chat", "hello")], ping=b"p1")
        assert decode_text(await next_binary(viewer)) == "hello"
        assert pong is not None
        await asyncio.wait_for(pong, 5)
        assert server.write_through.written == before + 1  # no task round: written through
        binary = [i for i, (_, op) in enumerate(written) if op == 0x2]
        pongs = [i for i, (_, op) in enumerate(written) if op == 0xA]
        assert len(binary) == 1 and len(pongs) == 1
        assert written[binary[0]][0] != written[pongs[0]][0]  # the viewer's, the robot's
        assert binary[0] < pongs[0]  # relayed first, then the sender's own pong


async def test_a_paused_receiver_falls_back_to_its_task_and_loses_nothing(
    make_server: Callable[..., RelayServer],
) -> None:
    # A burst of no_drop frames, many per read, to a viewer that stops reading: its
    # transport passes its write limit, so later frames wait for the writer task. All
    # arrive once, in order, when it reads again.
    limits = ServerLimits(outbound_no_drop_messages=4096)
    count = 2000
    blob = "x" * 2000
    async with make_server(limits=limits) as srv, client(srv, token=BOB_TOKEN) as viewer, \
            client(srv, source="127.0.0.2", create_connection=BatchedClient) as robot:
        await subscribe(viewer, "/husky1/.*")
        assert isinstance(robot, BatchedClient)
        viewer.transport.pause_reading()
        for start in range(0, count, 100):
            await robot.send_frames([
                string_frame("/husky1/events", f"{i}:{blob}", no_drop=True, seq=i + 1)
                for i in range(start, start + 100)])
        peer = max(srv.core.peers.values(), key=lambda p: p.peer_id if "bob" in p.label else -1)
        await wait_for(lambda: len(peer.outbound) > 0)  # the socket is full: queued
        assert srv.write_through.written > 0
        viewer.transport.resume_reading()
        got = [decode_text(await next_binary(viewer)).split(":")[0] for _ in range(count)]
        assert got == [str(i) for i in range(count)]
        assert peer.outbound.dropped_total == 0
