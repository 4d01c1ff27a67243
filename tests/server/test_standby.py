"""Integration: a robot's standby connection (``X-Fleetctl-Standby: 1``) on a real relay
(127.0.0.1:0) with real websockets clients; and the auth map reload of a standby, driven
through the relay core."""

from __future__ import annotations

import asyncio
import ipaddress
import json
import logging
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import InvalidStatus

from fleetctl.server.app import RelayServer
from fleetctl.server.peer import Peer
from fleetctl.server.sessions import SESSION_HEADER, STANDBY_HEADER
from fleetctl.wire.control import encode_subscription
from tests.server.conftest import (
    ALICE_TOKEN,
    AUTH,
    auth_map,
    client,
    next_binary,
    next_json,
    subscribe,
    wait_for,
)
from tests.server.test_app import closed_code, http_get
from tests.server.test_sessions import drain, make_core
from tests.support import decode_text, string_frame

ROBOT = "127.0.0.2"  # husky1 by address
SESSION = "husky1"
KEY = (("husky1",), SESSION)
GOAL = "/husky1/goal_pose"  # husky1 may receive it
ODOM = "/husky1/odom"  # husky1 may send it
ACTIVATE = json.dumps({"type": "activate"})


def robot(srv: RelayServer, *, standby: bool = False, session: str = SESSION) -> Any:
    """husky1 naming *session* on the upgrade, as a standby connection if *standby*."""
    headers = {SESSION_HEADER: session}
    if standby:
        headers[STANDBY_HEADER] = "1"
    return client(srv, source=ROBOT, additional_headers=headers)


async def next_text(ws: ClientConnection, timeout_s: float = 5.0) -> dict[str, Any]:
    """The very next message, which must be a text frame."""
    msg = await asyncio.wait_for(ws.recv(), timeout_s)
    assert isinstance(msg, str), f"a binary frame where a text frame was due: {msg!r:.80}"
    data: dict[str, Any] = json.loads(msg)
    return data


def standby_peer(srv: RelayServer, key: tuple[tuple[str, ...], str] = KEY) -> Peer:
    return srv.core.standbys[key]


async def test_upgrade_responses_advertise_standby(server: RelayServer) -> None:
    async with client(server, token=ALICE_TOKEN) as plain, robot(server, standby=True) as sb:
        assert plain.response.headers.get_all(STANDBY_HEADER) == ["1"]
        assert sb.response.headers.get_all(STANDBY_HEADER) == ["1"]


async def test_standby_is_welcomed_and_sent_nothing_else(server: RelayServer) -> None:
    async with robot(server) as main, client(server, token=ALICE_TOKEN) as alice:
        assert (await next_json(main, "session"))["resumed"] is False
        assert (await subscribe(main, GOAL))["type"] == "subscribed"
        async with robot(server, standby=True) as standby:
            welcome = await next_text(standby)
            assert welcome["type"] == "welcome" and welcome["identities"] == ["husky1"]
            await wait_for(lambda: KEY in server.core.standbys)
            peer = standby_peer(server)
            assert peer.session is None and peer.standby
            (session,) = server.core.sessions
            assert session.attached is not None and session.attached is not peer
            for i in range(3):  # droppable: nothing of it could come back in a mailbox
                await alice.send(string_frame(GOAL, f"go{i}"))
                assert decode_text(await next_binary(main)) == f"go{i}"
            # Delivered to the session's connection; nothing was queued for the standby.
            assert peer not in server.core.subs.receivers(GOAL)
            assert len(peer.outbound) == 0 and peer.outbound.ack_mark() is None
            _, metrics = await http_get(server.port, "/metrics")
            assert "fleetctl_standby_connections 1.0" in metrics
            # What the standby reads next is the answer to its activation: it was sent
            # nothing (no frame, no ack ping) before.
            await standby.send(ACTIVATE)
            assert (await next_text(standby))["type"] == "welcome"


async def test_activate_takes_the_session_over(server: RelayServer,
                                               caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="fleetctl.server")
    async with robot(server) as main, client(server, token=ALICE_TOKEN) as alice:
        await next_json(main, "session")
        assert (await subscribe(main, GOAL))["type"] == "subscribed"
        assert (await subscribe(alice, ODOM))["type"] == "subscribed"
        async with robot(server, standby=True) as standby:
            assert (await next_text(standby))["type"] == "welcome"
            await wait_for(lambda: KEY in server.core.standbys)
            # Back to back: the frame after the activation is relayed, not discarded.
            await standby.send(ACTIVATE)
            await standby.send(string_frame(ODOM, "first on the new connection"))
            welcome = await next_text(standby)
            assert welcome["type"] == "welcome" and welcome["identities"] == ["husky1"]
            session = await next_text(standby)
            assert session["type"] == "session" and session["name"] == SESSION
            assert session["resumed"] is True and session["subscriptions"] == [GOAL]
            assert (await next_text(standby)) == {"type": "subscribed", "topic_regex": GOAL}
            assert await closed_code(main) == 4409
            assert decode_text(await next_binary(alice)) == "first on the new connection"
            assert not server.core.standbys and server.metrics.errors.get("standby") is None
            (record,) = server.core.sessions
            assert record.attached is not None and not record.attached.standby
            await alice.send(string_frame(GOAL, "resumed"))
            assert decode_text(await next_binary(standby)) == "resumed"
    assert any(r.getMessage().endswith("activated its standby for session husky1")
               and r.levelno == logging.INFO for r in caplog.records)


async def test_newer_standby_replaces_the_older_of_its_session_only(
        server: RelayServer) -> None:
    async with robot(server, standby=True) as first, \
            robot(server, standby=True, session="husky1-b") as other:
        assert (await next_text(first))["type"] == "welcome"
        assert (await next_text(other))["type"] == "welcome"
        await wait_for(lambda: len(server.core.standbys) == 2)
        other_peer = standby_peer(server, (("husky1",), "husky1-b"))
        async with robot(server, standby=True) as second:
            assert (await next_text(second))["type"] == "welcome"
            assert await closed_code(first) == 4409
            assert first.close_reason == "standby replaced by a newer one"
            await wait_for(lambda: len(server.core.peers) == 2)  # the first one is gone
            assert len(server.core.standbys) == 2
            assert standby_peer(server, (("husky1",), "husky1-b")) is other_peer
            assert not other_peer.closing
            await other.send(ACTIVATE)  # still open, and still its session's standby
            assert (await next_text(other))["type"] == "welcome"
            assert (await next_text(other))["type"] == "session"
            assert server.metrics.closes == {4409: 1}


async def test_a_closed_standby_leaves_the_map(server: RelayServer) -> None:
    async with robot(server, standby=True) as first:
        assert (await next_text(first))["type"] == "welcome"
        await wait_for(lambda: KEY in server.core.standbys)
    await wait_for(lambda: not server.core.standbys and not server.core.peers)
    async with robot(server, standby=True) as again:
        assert (await next_text(again))["type"] == "welcome"
        await wait_for(lambda: KEY in server.core.standbys)
        assert server.metrics.closes == {}  # it replaced nothing
        await again.send(ACTIVATE)
        assert (await next_text(again))["type"] == "welcome"
        assert (await next_text(again))["resumed"] is False


@pytest.mark.parametrize(("headers", "why"), [
    ([(SESSION_HEADER, SESSION), (STANDBY_HEADER, "2")], "'2' is not 1"),
    ([(SESSION_HEADER, SESSION), (STANDBY_HEADER, "1"), (STANDBY_HEADER, "1")],
     f"2 {STANDBY_HEADER} headers"),
    ([(STANDBY_HEADER, "1")], f"{STANDBY_HEADER} without {SESSION_HEADER}"),
])
async def test_bad_standby_headers_are_refused_with_400(
        server: RelayServer, headers: list[tuple[str, str]], why: str) -> None:
    with pytest.raises(InvalidStatus) as refused:
        async with connect(f"ws://127.0.0.1:{server.port}/", local_addr=(ROBOT, 0),
                           additional_headers=headers):
            pass
    response = refused.value.response
    assert response.status_code == 400
    body = response.body.decode()
    assert STANDBY_HEADER in body and why in body
    assert not server.core.peers


async def test_activate_on_a_normal_connection_is_an_error(server: RelayServer) -> None:
    async with robot(server) as main:
        await next_json(main, "session")
        await main.send(ACTIVATE)
        error = await next_json(main, "error")
        assert error["code"] == "not_standby"
        assert (await subscribe(main, GOAL))["type"] == "subscribed"  # still open
        assert server.metrics.errors["not_standby"] == 1 and server.metrics.closes == {}


async def test_binary_frames_of_a_standby_are_discarded(server: RelayServer) -> None:
    async with client(server, token=ALICE_TOKEN) as alice, \
            robot(server, standby=True) as standby, client(server, source=ROBOT) as sender:
        assert (await subscribe(alice, "/husky1/.*"))["type"] == "subscribed"
        assert (await next_text(standby))["type"] == "welcome"
        frame = string_frame(ODOM, "from the standby")
        await standby.send(frame)  # a complete frame: the relay's frame sink
        error = await next_text(standby)
        assert error["type"] == "error" and error["code"] == "standby"
        await standby.send([frame[:10], frame[10:]])  # fragmented: the recv() path
        await standby.send(encode_subscription(GOAL))  # no subscription either
        await wait_for(lambda: server.metrics.errors.get("standby") == 3)
        peer = standby_peer(server)
        assert not server.core.subs.patterns(peer) and not peer.closing
        # Had the standby's frames been relayed, Alice would read them first.
        await sender.send(string_frame(ODOM, "from a normal connection"))
        assert decode_text(await next_binary(alice)) == "from a normal connection"
        assert server.metrics.messages_in[ODOM] == 1
        # One error frame for all three: the next text frame answers the activation.
        await standby.send(ACTIVATE)
        assert (await next_text(standby))["type"] == "welcome"


def test_auth_reload_sends_a_standby_nothing() -> None:
    core = make_core()
    closes: list[tuple[int, str]] = []
    standby = core.new_peer(ROBOT, lambda c, r: closes.append((c, r)), None,
                            session_name=SESSION, standby=True)
    core.authenticate(standby, core.auth.match_address(ipaddress.ip_address(ROBOT)))
    texts, _ = drain(standby)
    assert [t["type"] for t in texts] == ["welcome"] and core.standbys == {KEY: standby}
    raw = json.loads(json.dumps(AUTH))
    raw["identities"][0]["rules"].append({"topic": "/husky1/extra", "op": "receive"})
    assert core.reload_auth(auth_map(raw)) == (1, 0)
    assert drain(standby) == ([], []) and core.standbys == {KEY: standby} and not closes
    core.activate(standby)
    texts, _ = drain(standby)
    assert [t["type"] for t in texts] == ["welcome", "session"]
    assert {"topic": "/husky1/extra", "op": "receive"} in texts[0]["rules"]
    assert not core.standbys and standby.session is not None


async def test_a_standby_gets_no_keepalive_pings_until_it_activates(
        server: RelayServer) -> None:
    """A server ping sent into a cut would hold back every server frame after the
    activation until TCP retransmitted it: a standby is not pinged until it activates."""
    assert server._server is not None
    async with robot(server, standby=True) as standby:
        assert (await next_text(standby))["type"] == "welcome"
        await wait_for(lambda: KEY in server.core.standbys)
        connections = server._server.connections
        assert len(connections) == 1
        (conn,) = connections
        assert conn.ping_interval is None and conn.keepalive_task is None
        await standby.send(ACTIVATE)
        assert (await next_text(standby))["type"] == "welcome"
        await wait_for(lambda: conn.keepalive_task is not None)
        assert conn.ping_interval == 20  # websockets' default, as for every connection
