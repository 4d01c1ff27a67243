"""Stores in the sessions' stream: acknowledgements taken oldest first, timeouts, refusals.

A stand-in for nats-py's client records the publishes; the acknowledgements are handed to
the subscription's callback as JetStream words them. The real stream is exercised in
test_sharedsessions.py and test_replicas.py.
"""

from __future__ import annotations

import json
from typing import Any

from nats.aio.msg import Msg
from nats.errors import MaxPayloadError
from nats.js.errors import APIError, NoStreamResponseError, ServiceUnavailableError

from fleetctl.server.cluster.streamstores import StreamStores
from tests.support import ManualClock


class Nats:
    """What :class:`StreamStores` asks of nats-py's client."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, bytes, str, dict[str, str]]] = []
        self.acks: Any = None
        self.refuse: Exception | None = None

    def new_inbox(self) -> str:
        return "_INBOX.abc"

    async def subscribe(self, subject: str, cb: Any) -> Any:
        assert subject == "_INBOX.abc.*"
        self.acks = cb
        return self

    async def unsubscribe(self) -> None:
        pass

    async def publish(self, subject: str, payload: bytes, reply: str,
                      headers: dict[str, str]) -> None:
        if self.refuse is not None:
            raise self.refuse
        self.sent.append((subject, payload, reply, dict(headers)))

    async def answer(self, reply: str, data: bytes, headers: dict[str, str] | None = None
                     ) -> None:
        await self.acks(Msg(self, subject=reply, data=data, headers=headers))  # type: ignore[arg-type]


def stores(clock: ManualClock | None = None) -> tuple[StreamStores, dict[str, int], list[int]]:
    counters = {"stored": 0, "duplicates": 0}
    wakes: list[int] = []
    return (StreamStores("S", 2, 1.0, lambda: wakes.append(1), counters, clock or ManualClock()),
            counters, wakes)


def ack(seq: int, duplicate: bool = False) -> bytes:
    answer: dict[str, Any] = {"stream": "S", "seq": seq}
    if duplicate:
        answer["duplicate"] = True
    return json.dumps(answer).encode()


async def test_frames_are_published_with_a_reply_each_and_retired_oldest_first() -> None:
    s, counters, wakes = stores()
    nc = Nats()
    await s.start(nc)  # type: ignore[arg-type]
    await s.send(nc, "f_nd.a", b"one", {"Nats-Msg-Id": "d1"})  # type: ignore[arg-type]
    await s.send(nc, "f_nd.a", b"two", {"Nats-Msg-Id": "d2"})  # type: ignore[arg-type]
    assert not s.has_room() and len(s) == 2
    assert [(subject, frame, reply) for subject, frame, reply, _ in nc.sent] == [
        ("f_nd.a", b"one", "_INBOX.abc.0"), ("f_nd.a", b"two", "_INBOX.abc.1")]
    assert nc.sent[0][3] == {"Nats-Msg-Id": "d1", "Nats-Expected-Stream": "S"}
    # The second is acknowledged first: it waits for the first.
    await nc.answer("_INBOX.abc.1", ack(2, duplicate=True))
    assert s.oldest() == (False, None) and wakes == [1]
    await nc.answer("_INBOX.abc.0", ack(1))
    assert s.oldest() == (True, None) and s.oldest() == (True, None)
    assert s.oldest() == (False, None) and len(s) == 0 and s.has_room()
    assert counters == {"stored": 1, "duplicates": 1}


async def test_an_acknowledgement_that_does_not_come_is_a_timeout() -> None:
    clock = ManualClock()
    s, _, _ = stores(clock)
    nc = Nats()
    await s.start(nc)  # type: ignore[arg-type]
    await s.send(nc, "f_nd.a", b"one", {})  # type: ignore[arg-type]
    clock.now_s += 0.4
    wait_s = s.wait_s()
    assert s.oldest() == (False, None) and wait_s is not None and abs(wait_s - 0.6) < 1e-9
    clock.now_s += 0.6
    finished, error = s.oldest()
    assert finished and isinstance(error, TimeoutError) and s.wait_s() is None


async def test_refusals_and_no_leader_are_the_frames_outcome() -> None:
    s, counters, _ = stores()
    nc = Nats()
    await s.start(nc)  # type: ignore[arg-type]
    await s.send(nc, "f_nd.a", b"big", {})  # type: ignore[arg-type]
    await s.send(nc, "f_nd.a", b"x", {})  # type: ignore[arg-type]
    error = {"code": 400, "err_code": 10054, "description": "message size exceeds maximum"}
    await nc.answer("_INBOX.abc.0", json.dumps({"error": error}).encode())
    await nc.answer("_INBOX.abc.1", b"", {"Status": "503"})
    finished, first = s.oldest()
    assert finished and isinstance(first, APIError) and first.code == 400
    finished, second = s.oldest()
    assert finished and isinstance(second, NoStreamResponseError)
    await s.send(nc, "f_nd.a", b"y", {})  # type: ignore[arg-type]
    electing = {"code": 503, "err_code": 10008,
                "description": "JetStream system temporarily unavailable"}
    await nc.answer("_INBOX.abc.2", json.dumps({"error": electing}).encode())
    assert isinstance(s.oldest()[1], ServiceUnavailableError)
    nc.refuse = MaxPayloadError()  # nats-py refuses it before it leaves
    await s.send(nc, "f_nd.a", b"z" * 10, {})  # type: ignore[arg-type]
    assert isinstance(s.oldest()[1], MaxPayloadError)
    assert counters == {"stored": 0, "duplicates": 0}


async def test_forgotten_frames_late_acknowledgements_and_garbage_are_ignored() -> None:
    s, counters, wakes = stores()
    nc = Nats()
    await s.start(nc)  # type: ignore[arg-type]
    await s.send(nc, "f_nd.a", b"one", {})  # type: ignore[arg-type]
    s.forget()  # a failure: everything out is sent again
    await s.send(nc, "f_nd.a", b"one", {})  # type: ignore[arg-type]
    await nc.answer("_INBOX.abc.0", ack(1))  # the first copy's, late
    await nc.answer("_INBOX.abc.zzz", ack(1))
    await nc.answer("_INBOX.abc.7", ack(1))  # never sent
    assert s.oldest() == (False, None) and wakes == [] and counters["stored"] == 0
    await nc.answer("_INBOX.abc.1", b"not json")
    finished, error = s.oldest()
    assert finished and isinstance(error, APIError)
    for garbage in (b"[1]", b'{"error": 5}', b'{"error": {"bogus": 1}}'):
        await s.send(nc, "f_nd.a", b"x", {})  # type: ignore[arg-type]
        await nc.answer(f"_INBOX.abc.{s._next - 1}", garbage)
        finished, error = s.oldest()
        assert finished and isinstance(error, APIError), garbage


async def test_a_skipped_frame_keeps_its_place() -> None:
    s, _, _ = stores()
    nc = Nats()
    await s.start(nc)  # type: ignore[arg-type]
    await s.send(nc, "f_nd.a", b"one", {})  # type: ignore[arg-type]
    s.skip()  # a subject too long to publish
    assert s.oldest() == (False, None)  # behind the first
    await nc.answer("_INBOX.abc.0", ack(1))
    assert s.oldest() == (True, None) and s.oldest() == (True, None) and len(s) == 0
