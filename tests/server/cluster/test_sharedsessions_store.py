"""The replica's store loop, without NATS: no_drop frames leave the store queue only once
stored, in order, whatever order their acknowledgements come in and whichever fail.

A stand-in for nats-py's client records the publishes and the test answers them as
JetStream would (the real stream: test_sharedsessions.py, test_replicas.py).
"""

from __future__ import annotations

import asyncio
import json
from typing import Any

from nats.aio.msg import Msg

from fleetctl.server.cluster.config import ClusterConfig
from fleetctl.server.cluster.sharedsessions import SharedSessions
from tests.support import wait_until


class Nats:
    """What the store loop asks of nats-py's client."""

    is_connected = True

    def __init__(self) -> None:
        self.sent: list[tuple[bytes, str]] = []  # (frame, reply subject)
        self.acks: Any = None

    def new_inbox(self) -> str:
        return "_INBOX.t"

    async def subscribe(self, subject: str, cb: Any) -> Any:
        self.acks = cb
        return self

    async def unsubscribe(self) -> None:
        pass

    async def publish(self, subject: str, payload: bytes, reply: str,
                      headers: dict[str, str]) -> None:
        self.sent.append((payload, reply))

    async def answer(self, index: int, data: bytes, headers: dict[str, str] | None = None
                     ) -> None:
        reply = self.sent[index][1]
        await self.acks(Msg(self, subject=reply, data=data, headers=headers))  # type: ignore[arg-type]


def stored(seq: int) -> bytes:
    return json.dumps({"stream": "fleetctl_nodrop", "seq": seq}).encode()


async def started() -> tuple[SharedSessions, Nats, asyncio.Task[None]]:
    shared = SharedSessions(ClusterConfig(name="relay-a", nats_urls=("nats://h:4222",)),
                            3600.0)
    nats = Nats()
    shared._nc = nats  # type: ignore[assignment]
    return shared, nats, asyncio.create_task(shared._publish_loop())


async def test_frames_leave_the_queue_in_order_as_they_are_stored() -> None:
    shared, nats, task = await started()
    try:
        for frame in (b"e1", b"e2", b"e3"):
            shared.offer("/husky1/events", frame)
        await wait_until(lambda: len(nats.sent) == 3, 5.0)  # each went out at once
        await nats.answer(2, stored(3))
        await nats.answer(1, stored(2))
        assert len(shared._queue) == 3 and shared.acks.done == 0  # e1 not stored yet
        await nats.answer(0, stored(1))
        assert len(shared._queue) == 0 and shared.acks.done == 3
        assert shared.counters["stored"] == 3
    finally:
        task.cancel()


async def test_a_failed_store_keeps_its_frame_though_a_later_one_is_acknowledged() -> None:
    shared, nats, task = await started()
    try:
        shared.offer("/husky1/events", b"e1")
        shared.offer("/husky1/events", b"e2")
        await wait_until(lambda: len(nats.sent) == 2, 5.0)
        await nats.answer(0, b"", {"Status": "503"})  # no stream leader for e1
        await nats.answer(1, stored(1))  # e2 stored (the leader is back)
        # e1 is still queued, first: it and everything after it go out again.
        assert [q.frame for q in shared._queue] == [b"e1", b"e2"]
        await wait_until(lambda: len(nats.sent) == 4, 5.0)
        assert [frame for frame, _ in nats.sent] == [b"e1", b"e2", b"e1", b"e2"]
        assert shared.counters["store_failures"] == 1 and shared.stream_away()
        await nats.answer(0, stored(1))  # the first e1's late answer: ignored
        assert len(shared._queue) == 2
        await nats.answer(2, stored(2))
        await nats.answer(3, json.dumps({"stream": "fleetctl_nodrop", "seq": 1,
                                         "duplicate": True}).encode())
        assert len(shared._queue) == 0 and not shared.stream_away()
        # What JetStream did: e2 stored (first copy), e1 stored, e2 again a duplicate.
        assert shared.counters["stored"] == 2 and shared.counters["duplicates"] == 1
    finally:
        task.cancel()
