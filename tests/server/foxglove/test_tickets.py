"""Tickets: the book (single use, expiry, bounds) and the live endpoint and handshake."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from websockets.exceptions import ConnectionClosed

from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import Identity
from fleetctl.server.foxglove.tickets import TicketBook, TicketBookFull
from tests.server.conftest import ALICE_TOKEN, AUTH, BOB_TOKEN, auth_map
from tests.server.foxglove.fxclient import Viewer, https_get, open_viewer, ticket
from tests.support import ManualClock


def identity(name: str) -> Identity:
    found = next(i for i in auth_map().identities if i.name == name)
    return found


def test_a_ticket_works_once() -> None:
    book = TicketBook()
    value = book.issue(identity("alice"))
    assert book.redeem(value) == identity("alice")
    assert book.redeem(value) is None
    assert book.redeem("made-up") is None
    assert (book.issued, book.redeemed, book.refused) == (1, 1, 2)
    burnt = book.issue(identity("alice"))
    assert book.redeem(burnt, accept=False) is None and book.redeem(burnt) is None
    assert (book.redeemed, book.refused) == (1, 4)


def test_a_ticket_expires() -> None:
    clock = ManualClock()
    book = TicketBook(ttl_s=60.0, clock=clock)
    value = book.issue(identity("alice"))
    clock.now_s += 60.0
    assert book.redeem(value) is None
    book.issue(identity("alice"))
    clock.now_s += 61.0
    book.issue(identity("bob"))  # issuing sweeps expired tickets
    assert len(book) == 1


def test_the_book_is_bounded() -> None:
    book = TicketBook(max_tickets=3, max_per_identity=2)
    first = book.issue(identity("alice"))
    book.issue(identity("alice"))
    book.issue(identity("alice"))  # a third for alice evicts her oldest
    assert book.redeem(first) is None and len(book) == 2
    book.issue(identity("bob"))
    with pytest.raises(TicketBookFull):
        book.issue(identity("bob"))


def test_no_ticket_in_a_repr() -> None:
    book = TicketBook()
    value = book.issue(identity("alice"))
    assert value not in repr(book) and value not in repr(book.__dict__)


async def closed_with(port: int, ticket_value: str | None, secure: bool = True,
                      ) -> tuple[int, str, list[str]]:
    """Connect, read until the server closes; ``(code, reason, status messages)``."""
    async with open_viewer(port, ticket_value, secure) as ws:
        viewer = Viewer(ws)
        with pytest.raises(ConnectionClosed) as closed:
            await viewer.until(lambda: False)
        assert closed.value.rcvd is not None
        return (closed.value.rcvd.code, closed.value.rcvd.reason,
                [s["message"] for s in viewer.statuses])


async def test_used_ticket_is_refused_with_a_clear_close(fx_server: RelayServer) -> None:
    port = fx_server.web_port
    value = await ticket(port, ALICE_TOKEN)
    async with open_viewer(port, value) as ws:
        viewer = Viewer(ws)
        await viewer.until(lambda: viewer.server_info is not None)
    code, reason, statuses = await closed_with(port, value)
    assert code == 4401 and "already used" in reason and "already used" in statuses[0]


async def test_absent_wrong_or_expired_ticket_is_refused(fx_server: RelayServer) -> None:
    port = fx_server.web_port
    code, reason, _ = await closed_with(port, None)
    assert code == 4401 and "ticket" in reason
    code, reason, _ = await closed_with(port, "not-a-ticket")
    assert code == 4401 and "unknown" in reason
    fx_server.foxglove.tickets.ttl_s = 0.0  # every ticket is expired when it is used
    code, reason, _ = await closed_with(port, await ticket(port, ALICE_TOKEN))
    assert code == 4401 and "expired" in reason


async def test_ticket_endpoint_needs_a_token_and_tls(fx_server: RelayServer) -> None:
    port = fx_server.web_port
    status, body = await https_get(port, "/foxglove/ticket", BOB_TOKEN)
    answer = json.loads(body)
    assert status == 200 and answer["expires_in_s"] == 60.0
    assert answer["url"] == f"wss://127.0.0.1:{port}/?ticket={answer['ticket']}"
    assert (await https_get(port, "/foxglove/ticket"))[0] == 401
    assert (await https_get(port, "/foxglove/ticket", "wrong-token"))[0] == 401
    # The plain relay port: no ticket issued, and a ticket sent there is burnt.
    status, body = await https_get(fx_server.port, "/foxglove/ticket", ALICE_TOKEN,
                                   secure=False)
    assert status == 403 and b"TLS" in body
    value = await ticket(port, ALICE_TOKEN)
    code, reason, _ = await closed_with(fx_server.port, value, secure=False)
    assert code == 4401 and "TLS" in reason
    code, reason, _ = await closed_with(port, value)
    assert code == 4401 and "already used" in reason


async def test_fleetctl_clients_are_unaffected(fx_server: RelayServer, tmp_path: Path) -> None:
    from tests.server.conftest import client, next_json

    async with client(fx_server, token=ALICE_TOKEN) as ws:  # no subprotocol offered
        assert ws.subprotocol is None
        assert (await next_json(ws, "welcome"))["identities"] == ["alice"]


async def test_ticket_of_a_revoked_token_is_refused(fx_server: RelayServer) -> None:
    port = fx_server.web_port
    value = await ticket(port, ALICE_TOKEN)
    raw = {**AUTH, "identities": [i for i in AUTH["identities"] if i["name"] != "alice"]}
    fx_server.core.reload_auth(auth_map(raw))
    code, reason, _ = await closed_with(port, value)
    assert code == 4401 and "no longer valid" in reason
