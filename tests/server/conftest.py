"""Shared helpers of the server tests: auth maps, frames, a live relay on port 0."""

from __future__ import annotations

import asyncio
import hashlib
import ipaddress
import json
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection, connect

from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import AuthMap, parse_auth_map
from fleetctl.server.config import ServerConfig, ServerLimits
from fleetctl.server.relay import Peer, RelayCore
from tests.support import wait_until

ALICE_TOKEN = "alice-secret-token"
BOB_TOKEN = "bob-secret-token"


def sha(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


AUTH = {
    "version": 1,
    "identities": [
        {
            "name": "husky1",
            "ip": "127.0.0.2",
            "rules": [
                {"topic": "/husky1/.*", "op": "send"},
                {"topic": "/husky1/(goal_pose|initialpose)", "op": "receive"},
            ],
        },
        {
            "name": "husky2",
            "ip": "127.0.0.3",
            "rules": [{"topic": "/husky2/.*", "op": "send"}],
        },
        {"name": "alice", "token_sha256": sha(ALICE_TOKEN),
         "rules": [{"topic": ".*", "op": "both"}]},
        {"name": "bob", "token_sha256": sha(BOB_TOKEN),
         "rules": [{"topic": "/husky1/.*", "op": "receive"}]},
    ],
}


def auth_map(raw: dict[str, Any] | None = None) -> AuthMap:
    return parse_auth_map(raw or AUTH, Path("test-auth.yaml"))


async def wait_for(predicate: Callable[[], bool], timeout_s: float = 5.0) -> None:
    """:func:`tests.support.wait_until` with this package's default deadline."""
    await wait_until(predicate, timeout_s)


async def next_json(ws: ClientConnection, kind: str, timeout_s: float = 5.0) -> dict[str, Any]:
    """Return the next text frame of ``type`` *kind*, skipping binary and other frames."""

    async def scan() -> dict[str, Any]:
        while True:
            msg = await ws.recv()
            if isinstance(msg, str):
                data: dict[str, Any] = json.loads(msg)
                if data.get("type") == kind:
                    return data

    return await asyncio.wait_for(scan(), timeout_s)


async def next_binary(ws: ClientConnection, timeout_s: float = 5.0) -> bytes:
    async def scan() -> bytes:
        while True:
            msg = await ws.recv()
            if isinstance(msg, bytes):
                return msg

    return await asyncio.wait_for(scan(), timeout_s)


@pytest.fixture
def make_server(tmp_path: Path) -> Callable[..., RelayServer]:
    def factory(**kwargs: Any) -> RelayServer:
        auth = kwargs.pop("auth", None) or auth_map()
        limits = kwargs.pop("limits", ServerLimits())
        config = ServerConfig(
            listen_host=kwargs.pop("listen_host", "127.0.0.1"), listen_port=0,
            auth_map=tmp_path / "auth.yaml",
            database=kwargs.pop("database", tmp_path / "fleet.db"), limits=limits, **kwargs,
        )
        return RelayServer(config, auth)

    return factory


@pytest.fixture
async def server(make_server: Callable[..., RelayServer]) -> AsyncIterator[RelayServer]:
    async with make_server() as srv:
        yield srv


def client(
    srv: RelayServer, *, source: str = "127.0.0.1", token: str | None = None, **kw: Any
) -> Any:
    """Open a client to *srv* from loopback address *source*, with a Bearer *token*."""
    headers = dict(kw.pop("additional_headers", None) or {})
    if token:
        headers["Authorization"] = f"Bearer {token}"
    return connect(
        f"ws://127.0.0.1:{srv.port}/", local_addr=(source, 0), additional_headers=headers,
        max_size=None, compression=None, **kw,
    )


async def subscribe(ws: ClientConnection, pattern: str) -> dict[str, Any]:
    """Subscribe and return the server's answer (subscribed or error)."""
    from fleetctl.wire.control import encode_subscription

    await ws.send(encode_subscription(pattern))

    async def scan() -> dict[str, Any]:
        while True:
            msg = await ws.recv()
            if isinstance(msg, str):
                data: dict[str, Any] = json.loads(msg)
                if data["type"] in ("subscribed", "error"):
                    return data

    return await asyncio.wait_for(scan(), 5.0)


def raw_peer(core: RelayCore, address: str | None = None, session: str | None = None) -> Peer:
    """A relay-core connection that has not authenticated yet; its close requests are
    recorded (read them with :func:`closes`)."""
    requests: list[tuple[int, str]] = []
    p = core.new_peer(address, lambda c, r: requests.append((c, r)), None, session_name=session)
    p.closes = requests  # type: ignore[attr-defined]
    return p


def authed_peer(core: RelayCore, address: str | None = None, token: str | None = None, *,
            session: str | None = None) -> Peer:
    """A relay-core connection authenticated by its source *address* and/or *token*."""
    p = raw_peer(core, address, session)
    ids = core.auth.match_address(ipaddress.ip_address(address)) if address else []
    if token:
        ids.append(core.auth.match_token(token))  # type: ignore[arg-type]
    core.authenticate(p, ids)
    return p


def closes(p: Peer) -> list[tuple[int, str]]:
    """The (code, reason) close requests of a peer made by :func:`raw_peer`."""
    found: list[tuple[int, str]] = p.closes  # type: ignore[attr-defined]
    return found

