"""The standby connection's keeper (fleetctl.client.standby), with fake connections.

RobotLink's use of it through the real relay is in test_transport_standby.py.
"""

from __future__ import annotations

import asyncio
import random
import socket
from typing import Any

import pytest
from websockets.exceptions import ConnectionClosedOK
from websockets.frames import Close
from websockets.protocol import State

from fleetctl.client.standby import ACTIVATE, Standby
from tests.client.conftest import wait_until


class FakeTransport:
    def __init__(self, sock: Any) -> None:
        self.sock = sock
        self.aborted = False

    def get_extra_info(self, name: str) -> Any:
        return self.sock if name == "socket" else None

    def abort(self) -> None:
        self.aborted = True


class FakeWebSocket:
    """Yields what is put in ``inbox`` until ``end()``; then ends as a closed connection."""

    def __init__(self, sock: Any) -> None:
        self.state = State.OPEN
        self.transport = FakeTransport(sock)
        self.inbox: asyncio.Queue[str | None] = asyncio.Queue()
        self.close_rcvd: Close | None = None
        self.closed = False
        self.sent: list[str] = []
        self.send_fails = False  # closed by the peer, not yet seen by the state

    async def send(self, message: str) -> None:
        if self.state is not State.OPEN or self.send_fails:
            raise ConnectionClosedOK(Close(1001, "going away"), None)
        self.sent.append(message)

    def __aiter__(self) -> FakeWebSocket:
        return self

    async def __anext__(self) -> str:
        item = await self.inbox.get()
        if item is None:
            self.state = State.CLOSED
            raise ConnectionClosedOK(Close(1001, "going away"), None)
        return item

    def end(self) -> None:
        self.inbox.put_nowait(None)

    async def close(self, code: int = 1000, reason: str = "") -> None:
        self.closed = True
        self.state = State.CLOSED


class Harness:
    """Dials hand out numbered sockets; upgrades make FakeWebSockets; unacked per socket."""

    def __init__(self, fail_dials: int = 0) -> None:
        self.fail_dials = fail_dials
        self.dials = 0
        self.upgraded: list[FakeWebSocket] = []
        self.upgraded_socks: list[Any] = []
        self.unacked: dict[Any, int] = {}

    async def dial(self) -> tuple[socket.socket, int]:
        self.dials += 1
        if self.dials <= self.fail_dials:
            raise ConnectionRefusedError("refused")
        return f"sock{self.dials}", 0  # type: ignore[return-value]

    async def upgrade(self, sock: socket.socket, replica: int) -> FakeWebSocket:
        ws = FakeWebSocket(sock)
        self.upgraded.append(ws)
        self.upgraded_socks.append(sock)
        return ws

    def standby(self, **kw: Any) -> Standby:
        return Standby(self.upgrade, self.dial, lambda s: self.unacked.get(s, 0), **kw)

    async def opened(self, **kw: Any) -> Standby:
        """A keeper whose main connection works, once its standby is open."""
        keeper = self.standby(**kw)
        keeper.main_up(True)
        await wait_until(lambda: keeper.connection is not None)
        return keeper


async def test_nothing_is_opened_for_a_server_that_does_not_offer_it() -> None:
    h = Harness()
    keeper = h.standby()
    keeper.main_up(False)
    assert keeper._opener is None  # nothing started: no dial can follow
    assert keeper.connection is None and h.dials == 0
    assert await keeper.activate(0) is None
    await keeper.close()


async def test_it_opens_once_the_main_connection_works_and_is_taken_when_usable() -> None:
    h = Harness()
    keeper = h.standby()
    keeper.main_up(True)
    keeper.main_up(True)  # a second call while opening opens nothing more
    await wait_until(lambda: keeper.connection is not None)
    assert h.dials == 1 and len(h.upgraded) == 1
    ws = await keeper.activate(0)
    assert ws is h.upgraded[0] and not ws.transport.aborted
    assert ws.sent == [ACTIVATE]  # sent by the keeper, before anything of the caller's
    assert keeper.connection is None and keeper.stats()["activations"] == 1
    await keeper.close()


@pytest.mark.parametrize("case", ["other replica", "unacknowledged data", "closed"])
async def test_an_unusable_standby_is_closed_not_taken(case: str) -> None:
    h = Harness()
    keeper = await h.opened()
    ws = h.upgraded[0]
    replica = 1 if case == "other replica" else 0
    if case == "unacknowledged data":
        h.unacked[ws.transport.sock] = 2  # a write on it would wait for a retransmission
    if case == "closed":
        ws.state = State.CLOSING
    assert await keeper.activate(replica) is None
    assert ws.transport.aborted and keeper.stats()["unusable"] == 1
    assert ws.sent == []  # an unusable standby is not activated
    assert keeper.connection is None
    await keeper.close()


async def test_a_standby_that_closed_as_it_was_activated_is_still_handed_over() -> None:
    """The activation's send found it closed: no exception here; the caller's next send
    on it raises, and the link dials again (test_transport_standby.py)."""
    h = Harness()
    keeper = await h.opened()
    ws = h.upgraded[0]
    ws.send_fails = True
    assert await keeper.activate(0) is ws
    assert ws.sent == [] and not ws.transport.aborted
    await keeper.close()


async def test_an_adopted_socket_becomes_the_next_standby_without_a_dial() -> None:
    h = Harness()
    keeper = h.standby()
    keeper.adopt("dialed-by-the-link", 0)  # type: ignore[arg-type]
    assert keeper.connection is None  # not before the activated connection works
    keeper.main_up(True)
    await wait_until(lambda: keeper.connection is not None)
    assert h.dials == 0 and h.upgraded_socks == ["dialed-by-the-link"]
    await keeper.close()


async def test_a_failed_open_is_retried_later_with_a_growing_wait() -> None:
    h = Harness(fail_dials=2)
    keeper = h.standby(retry_min_s=0.01, retry_max_s=0.02)
    keeper.main_up(True)
    await wait_until(lambda: keeper.connection is not None)
    assert h.dials == 3 and keeper.stats()["open_failures"] == 2
    await keeper.close()


def test_the_retry_wait_doubles_with_jitter_under_its_cap() -> None:
    """A fleet whose standbys a relay restart closed at once must not retry in step: each
    wait is the doubling one (capped) times U(0.5, 1)."""
    keeper = Harness().standby(retry_min_s=1.0, retry_max_s=4.0, rng=random.Random(7))
    scheduled: list[float] = []
    keeper._open_soon = scheduled.append  # type: ignore[method-assign]
    returned = [keeper._retry_later() for _ in range(4)]
    draws = random.Random(7)
    expected = [base * draws.uniform(0.5, 1.0) for base in (1.0, 2.0, 4.0, 4.0)]
    assert scheduled == returned == expected
    assert len(set(returned)) == 4  # not in step with an unjittered fleet


async def test_nothing_is_opened_while_the_main_connection_is_down() -> None:
    h = Harness(fail_dials=1)
    keeper = h.standby(retry_min_s=0.01)
    keeper.main_up(True)
    await wait_until(lambda: h.dials == 1)
    keeper.main_down()  # the retry finds the main connection down and opens nothing
    await wait_until(lambda: keeper._opener is not None and keeper._opener.done())
    assert keeper.connection is None and h.dials == 1
    keeper.main_up(True)
    await wait_until(lambda: keeper.connection is not None)
    await keeper.close()


async def test_a_standby_the_server_closes_is_replaced() -> None:
    h = Harness()
    keeper = await h.opened(retry_min_s=0.01)
    first = h.upgraded[0]
    first.inbox.put_nowait('{"type": "welcome", "identities": ["r1"]}')
    first.end()
    await wait_until(lambda: keeper.connection is not None and keeper.connection is not first)
    assert keeper.stats()["lost"] == 1 and keeper.stats()["opened"] == 2
    await keeper.close()


async def test_close_closes_the_standby_and_opens_no_more() -> None:
    h = Harness()
    keeper = await h.opened(retry_min_s=0.01)
    ws = h.upgraded[0]
    await keeper.close()
    assert ws.closed and keeper.connection is None
    opener = keeper._opener
    keeper.main_up(True)
    assert keeper._opener is opener and opener is not None and opener.done()  # none new
    assert h.dials == 1
