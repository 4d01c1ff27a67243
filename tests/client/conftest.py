"""Helpers of the client link tests: a real relay on port 0, a TCP forwarder, consumers."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import socket
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection, connect

from fleetctl.client.config import ClientConfig, parse_client_config
from fleetctl.client.transport import RobotLink
from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import AuthMap, parse_auth_map
from fleetctl.server.config import ServerConfig
from fleetctl.wire.control import encode_subscription
from fleetctl.wire.fragments import Reassembler
from fleetctl.wire.metadata import read_metadata
from fleetctl.wire.whole_messages import whole_messages
from tests.support import decode_text
from tests.support import wait_until as wait_until_s

ROBOT_TOKEN = "robot-r1-token"
OPERATOR_TOKEN = "operator-token"


def sha(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


AUTH: dict[str, Any] = {
    "version": 1,
    "identities": [
        {"name": "r1", "token_sha256": sha(ROBOT_TOKEN),
         "rules": [{"topic": "/r1/.*", "op": "send"}, {"topic": "/r1/cmd.*", "op": "receive"}]},
        {"name": "r2", "ip": "127.0.0.2",
         "rules": [{"topic": "/r2/.*", "op": "send"}, {"topic": "/r2/cmd.*", "op": "receive"}]},
        {"name": "operator", "token_sha256": sha(OPERATOR_TOKEN),
         "rules": [{"topic": ".*", "op": "both"}]},
    ],
}


def auth_map() -> AuthMap:
    return parse_auth_map(AUTH, Path("test-auth.yaml"))


def make_server(tmp_path: Path, port: int = 0) -> RelayServer:
    config = ServerConfig(listen_host="127.0.0.1", listen_port=port,
                          auth_map=tmp_path / "auth.yaml", database=tmp_path / "fleet.db")
    return RelayServer(config, auth_map())


@pytest.fixture
async def server(tmp_path: Path) -> AsyncIterator[RelayServer]:
    async with make_server(tmp_path) as srv:
        yield srv


def robot_config(url: str, tmp_path: Path, **extra: Any) -> ClientConfig:
    """The r1 robot's config (token identity), with *extra* top-level fields."""
    (tmp_path / "r1.token").write_text(ROBOT_TOKEN + "\n")
    data: dict[str, Any] = {
        "server_url": url, "robot_name": "r1", "token_file": "r1.token",
        "publish": [
            {"topic": "/events", "type": "std_msgs/msg/String", "no_drop": True},
            {"topic": "/chatter", "type": "std_msgs/msg/String", "priority": 2.0},
        ],
        "subscribe": [{"remote_topic": "/r1/cmd.*", "type": "std_msgs/msg/String"}],
        **extra,
    }
    return parse_client_config(data, source="test-client.yaml", base_dir=tmp_path)



@contextlib.asynccontextmanager
async def running(link: RobotLink) -> AsyncIterator[RobotLink]:
    """*link* running in a task for the block; stopped (bounded) after it."""
    task = asyncio.create_task(link.run())
    try:
        yield link
    finally:
        await asyncio.wait_for(link.stop(), 5.0)
        await asyncio.wait_for(task, 5.0)


async def wait_until(predicate: Callable[[], bool], timeout_s: float = 10.0) -> None:
    """:func:`tests.support.wait_until` with this package's default deadline."""
    await wait_until_s(predicate, timeout_s)


class Consumer:
    """A token-authenticated plain WebSocket consumer that reassembles fragments."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.frames: list[bytes] = []
        self.reassembler = Reassembler(256 * 1024 * 1024, 30.0)
        self._task = asyncio.create_task(self._read())

    @classmethod
    @contextlib.asynccontextmanager
    async def open(cls, url: str, *patterns: str) -> AsyncIterator[Consumer]:
        async with connect(url, additional_headers={"Authorization": f"Bearer {OPERATOR_TOKEN}"},
                           max_size=None, compression=None, proxy=None) as ws:
            for pattern in patterns:
                await ws.send(encode_subscription(pattern))
                await _next_json(ws, "subscribed")
            consumer = cls(ws)
            try:
                yield consumer
            finally:
                consumer._task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await consumer._task

    async def _read(self) -> None:
        async for whole in whole_messages(self.ws, self.reassembler):
            self.frames.append(whole)

    def texts(self, topic: str | None = None) -> list[str]:
        return [decode_text(f) for f in self.frames
                if topic is None or read_metadata(f).topic == topic]


async def _next_json(ws: ClientConnection, kind: str) -> dict[str, Any]:
    async def scan() -> dict[str, Any]:
        while True:
            msg = await ws.recv()
            if isinstance(msg, str):
                data: dict[str, Any] = json.loads(msg)
                if data.get("type") == kind:
                    return data
                if data.get("type") == "error":
                    raise AssertionError(f"server error: {data}")

    return await asyncio.wait_for(scan(), 5.0)


class TcpForwarder:
    """A real TCP forwarder between the robot and the server, to cut or stall the link.

    ``stall()`` stops moving bytes on existing connections without closing them (a radio
    gone silent); ``refuse()`` closes everything and stops listening; ``accept()`` listens
    again on the same port. *mss* clamps the robot's TCP segments as a path of a smaller
    MTU does (WireGuard's 1420: 1368 bytes with timestamps).
    """

    def __init__(self, target_port: int, *, mss: int | None = None) -> None:
        self.target_port = target_port
        self.mss = mss
        self.port = 0
        self._server: asyncio.Server | None = None
        self._writers: list[asyncio.StreamWriter] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._stalled = asyncio.Event()

    async def accept(self) -> None:
        self._stalled.clear()
        if self.mss is None:
            self._server = await asyncio.start_server(self._handle, "127.0.0.1", self.port)
        else:  # advertised in the SYN-ACK: the robot's segments are this size at most
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_MAXSEG, self.mss)
            sock.bind(("127.0.0.1", self.port))
            self._server = await asyncio.start_server(self._handle, sock=sock)
        self.port = self._server.sockets[0].getsockname()[1]

    def stall(self) -> None:
        """Stall the current connections; new ones forward normally."""
        self._stalled.set()
        self._stalled = asyncio.Event()

    async def refuse(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
        for writer in self._writers:
            writer.transport.abort()
        self._writers.clear()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
        except OSError:
            writer.transport.abort()
            return
        self._writers += [writer, up_writer]
        for src, dst in ((reader, up_writer), (up_reader, writer)):
            task = asyncio.create_task(self._pump(src, dst, self._stalled))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _pump(self, src: asyncio.StreamReader, dst: asyncio.StreamWriter,
                    stalled: asyncio.Event) -> None:
        try:
            while data := await src.read(65536):
                if stalled.is_set():
                    await asyncio.Event().wait()  # hold the bytes forever: silent link
                dst.write(data)
                await dst.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            dst.transport.abort()
