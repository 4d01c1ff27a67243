"""The NATS users ``up --replicas`` writes, on a real nats-server with real replicas: each
replica works with its own credentials and permissions, and may do nothing else."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetctl.deploy.replicas import nats_permissions, password_hash
from fleetctl.server.app import RelayServer
from fleetctl.server.cluster.config import NatsCredentials
from fleetctl.server.sessions import SESSION_HEADER
from tests.server.cluster.conftest import fanout, replica_config
from tests.server.cluster.natsproc import NatsServer, nats_binary
from tests.server.conftest import (
    ALICE_TOKEN,
    auth_map,
    client,
    next_binary,
    next_json,
    subscribe,
    wait_for,
)
from tests.support import decode_text, string_frame

nats = pytest.importorskip("nats")
pytestmark = pytest.mark.skipif(nats_binary() is None, reason="no nats-server binary")


@pytest.fixture
def secured(tmp_path: Path) -> Iterator[NatsServer]:
    users = []
    for name in ("relay-1", "relay-2"):
        password = f"secret of {name}"
        (tmp_path / f"{name}.password").write_text(password + "\n")
        users.append({"user": name, "password": password_hash(password),
                      "permissions": nats_permissions()})
    server = NatsServer("secured", tmp_path, authorization={"users": users})  # type: ignore[dict-item]
    server.start()
    yield server
    server.stop()


def replica(tmp_path: Path, name: str, url: str) -> RelayServer:
    creds = NatsCredentials(user=name, password_file=tmp_path / f"{name}.password")
    return RelayServer(replica_config(tmp_path, name, [url], credentials=creds), auth_map())


async def test_replicas_relay_and_share_state_with_their_own_users(
        tmp_path: Path, secured: NatsServer) -> None:
    a, b = replica(tmp_path, "relay-1", secured.url), replica(tmp_path, "relay-2", secured.url)
    async with a, b:
        async with client(a, source="127.0.0.2") as robot, \
                client(b, token=ALICE_TOKEN) as viewer:
            await next_json(robot, "welcome")
            assert (await subscribe(viewer, "/husky1/chat"))["type"] == "subscribed"
            await wait_for(lambda: bool(fanout(b).subscribed), 10.0)
            for _ in range(200):  # interest reaches A's NATS connection asynchronously
                await robot.send(string_frame("/husky1/chat", "hello"))
                if b.metrics.messages_out.get("/husky1/chat"):
                    break
                await asyncio.sleep(0.05)  # probe period of a bounded wait
            assert b.metrics.messages_out.get("/husky1/chat")
            # The shared registry (KV) works under these permissions too.
            await wait_for(lambda: "husky1" in b.registry.names(), 10.0)
            # So do shared sessions: records (KV), the no_drop stream and its consumers.
            async with client(b, token=ALICE_TOKEN,
                              additional_headers={SESSION_HEADER: "console"}) as console:
                assert (await subscribe(console, "/husky1/events"))["type"] == "subscribed"
                held = b.core.sessions.shared
                assert held is not None
                await wait_for(lambda: held.counters["puts"] >= 2, 10.0)
                await robot.send(string_frame("/husky1/events", "e0", no_drop=True, seq=1))
                assert decode_text(await next_binary(console, 10.0)) == "e0"
        for side in (a, b):
            assert fanout(side).registry is not None
            assert fanout(side).registry.counters["put_failures"] == 0  # type: ignore[union-attr]
            sessions = side.core.sessions.shared
            assert sessions is not None
            assert sessions.counters["put_failures"] == sessions.counters["feed_failures"] \
                == sessions.counters["store_failures"] == sessions.counters["refused"] == 0


async def test_a_replica_user_may_not_publish_outside_the_fleet(
        tmp_path: Path, secured: NatsServer) -> None:
    errors: list[Exception] = []

    async def on_error(exc: Exception) -> None:
        errors.append(exc)

    nc = await nats.connect(secured.url, user="relay-1", password="secret of relay-1",
                            error_cb=on_error, allow_reconnect=False)
    try:
        await nc.publish("other.subject", b"x")
        await nc.publish("$JS.API.STREAM.DELETE.KV_fleetctl_robots", b"")
        await nc.publish("$JS.API.STREAM.PURGE.fleetctl_nodrop", b"")
        await nc.flush()
        await wait_for(lambda: len(errors) >= 3, 5.0)
    finally:
        await nc.close()
    assert all("permissions violation" in str(e).lower() for e in errors), errors
    with pytest.raises(Exception, match=r"[Aa]uthoriz"):
        await nats.connect(secured.url, user="relay-1", password="wrong",
                           allow_reconnect=False, max_reconnect_attempts=0)
