"""Issue 14, item 4 and the per-identity cap: what a connection may hold before it
authenticates, and how many connections one identity may have."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Callable

from fleetctl.server.admission import TokenBucket, UnauthenticatedGate
from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerLimits
from fleetctl.server.connection import PRE_AUTH_MAX_FRAME_BYTES
from tests.security.conftest import RawClient
from tests.server.conftest import ALICE_TOKEN, client, next_json, subscribe, wait_for


async def test_unauthenticated_fragmented_message_is_cut_at_a_few_kib(
    server: RelayServer,
) -> None:
    raw = await RawClient.open(server.port, source="127.0.0.9")  # no identity
    assert await raw.request() == 101
    chunk = b"\0" * 4096
    await raw.send_frame(0x2, chunk, fin=False)  # an unfinished fragmented message
    await raw.send_frame(0x0, chunk, fin=False)
    await raw.send_frame(0x0, chunk, fin=False)
    assert await raw.close_code() == 1009  # over PRE_AUTH_MAX_FRAME_BYTES, not 16 MiB
    raw.close()
    await wait_for(lambda: not server.core.peers and server.gate.open == 0)
    assert PRE_AUTH_MAX_FRAME_BYTES < 16 * 1024


async def test_authenticated_connections_get_the_full_frame_bound(server: RelayServer) -> None:
    async with client(server, source="127.0.0.9") as ws:
        await ws.send(json.dumps({"token": ALICE_TOKEN}))
        await next_json(ws, "welcome")
        assert (await subscribe(ws, "/big"))["type"] == "subscribed"
        from tests.support import string_frame
        big = string_frame("/big", "x" * 100_000)
        await ws.send(big)
        assert len(await asyncio.wait_for(ws.recv(), 5)) == len(big)
        assert server.gate.open == 0  # the slot was given back on authentication


async def test_unauthenticated_connections_are_capped_per_address(
    make_server: Callable[..., RelayServer],
) -> None:
    limits = ServerLimits(max_unauthenticated_per_address=3,
                          max_unauthenticated_connections=5)
    async with make_server(limits=limits) as srv:
        held = [await RawClient.open(srv.port, source="127.0.0.9") for _ in range(3)]
        await wait_for(lambda: srv.gate.open == 3)
        extra = await RawClient.open(srv.port, source="127.0.0.9")
        assert await extra.reader.read() == b""  # aborted at accept
        others = [await RawClient.open(srv.port, source="127.0.0.10") for _ in range(2)]
        await wait_for(lambda: srv.gate.open == 5)
        third = await RawClient.open(srv.port, source="127.0.0.11")  # total cap
        assert await third.reader.read() == b""
        assert srv.metrics.connections_refused == {"total": 1, "per_address": 1}
        for raw in [*held, *others]:
            raw.close()
        await wait_for(lambda: srv.gate.open == 0)
        async with client(srv, token=ALICE_TOKEN) as ws:  # room again
            await next_json(ws, "welcome")


async def test_auth_timeout_aborts_without_the_close_timeout(
    make_server: Callable[..., RelayServer],
) -> None:
    async with make_server(limits=ServerLimits(auth_timeout_s=0.2)) as srv:
        raw = await RawClient.open(srv.port, source="127.0.0.9")
        assert await raw.request() == 101
        started = time.monotonic()
        assert await raw.close_code() == 4403
        assert await raw.reader.read() == b""  # hung up without waiting for our close
        assert time.monotonic() - started < 3.0  # websockets' close timeout is 10 s
        await wait_for(lambda: not srv.core.peers and srv.gate.open == 0)


async def test_connections_per_identity_are_capped(
    make_server: Callable[..., RelayServer],
) -> None:
    async with make_server(limits=ServerLimits(max_connections_per_identity=2)) as srv:
        async with client(srv, token=ALICE_TOKEN) as a, client(srv, token=ALICE_TOKEN) as b:
            await next_json(a, "welcome")
            await next_json(b, "welcome")
            async with client(srv, token=ALICE_TOKEN) as c:
                await asyncio.wait_for(c.wait_closed(), 5)
                assert c.close_code == 4429 and "2 connections" in (c.close_reason or "")
        async with client(srv, token=ALICE_TOKEN) as d:  # counted down on close
            await next_json(d, "welcome")


def test_gate_and_bucket_arithmetic() -> None:
    gate = UnauthenticatedGate(3, 2, exempt=lambda a: a == "proxy")
    assert [gate.admit("a"), gate.admit("a"), gate.admit("a")] == [None, None, "per_address"]
    assert gate.admit("proxy") is None and gate.admit("proxy") == "total"
    gate.release("a")
    assert gate.admit("proxy") is None  # exempt from the per-address cap
    now = [0.0]
    bucket = TokenBucket(2.0, 3, clock=lambda: now[0])
    assert [bucket.take() for _ in range(4)] == [True, True, True, False]
    now[0] += 0.5
    assert [bucket.take(), bucket.take()] == [True, False]


async def test_robots_by_address_take_no_unauthenticated_slot(
    make_server: Callable[..., RelayServer],
) -> None:
    # Strangers holding every slot (half-sent requests) used to keep the fleet's robots,
    # authenticated by their WireGuard address, out too.
    limits = ServerLimits(max_unauthenticated_per_address=2,
                          max_unauthenticated_connections=2)
    async with make_server(limits=limits) as srv:
        held = [await RawClient.open(srv.port, source="127.0.0.9") for _ in range(2)]
        await wait_for(lambda: srv.gate.open == 2)
        stranger = await RawClient.open(srv.port, source="127.0.0.10")
        assert await stranger.reader.read() == b""  # aborted at accept: the total cap
        async with client(srv, source="127.0.0.2") as robot:  # husky1's address
            assert (await next_json(robot, "welcome"))["identities"] == ["husky1"]
            assert srv.gate.open == 2
        for raw in held:
            raw.close()
