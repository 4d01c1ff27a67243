"""A pong before the connection has an identity: the relay answers it only once the
connection is authenticated. A pong tells the client that what it sent before the ping
was taken (the robot's link forgets its no_drop messages on it), but a connection whose
token is refused has its frames discarded: its pong, sent as websockets parsed the
ping, made a client that trusts pongs lose the messages (the client soak lost 154-170
no_drop events per 20 s of refused token; docs/benchmarks.md, "Robot client soak")."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable

from fleetctl.server.app import RelayServer
from tests.server.conftest import ALICE_TOKEN, client, next_json
from tests.server.test_app import closed_code


async def test_no_pong_on_a_connection_whose_token_is_refused(
    make_server: Callable[..., RelayServer],
) -> None:
    async with make_server() as srv, client(srv) as ws:
        pong = await ws.ping()  # before the token: its frames are not taken yet
        await ws.send(json.dumps({"token": "not-a-token-of-this-fleet-at-all"}))
        assert await closed_code(ws) == 4401
        # Never answered: websockets fails the ping's waiter when the connection closes.
        assert not (pong.done() and not pong.cancelled() and pong.exception() is None)


async def test_a_pong_before_the_token_is_sent_once_the_token_is_accepted(
    make_server: Callable[..., RelayServer],
) -> None:
    async with make_server() as srv, client(srv) as ws:
        pong = await ws.ping()
        await ws.send(json.dumps({"token": ALICE_TOKEN}))
        await next_json(ws, "welcome")
        await asyncio.wait_for(pong, 5)


async def test_an_address_identity_is_answered_at_once(
    make_server: Callable[..., RelayServer],
) -> None:
    async with make_server() as srv, client(srv, source="127.0.0.2") as robot:
        await next_json(robot, "welcome")
        await asyncio.wait_for(await robot.ping(), 5)
