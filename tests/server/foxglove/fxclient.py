"""A Foxglove WebSocket protocol v1 test client, written from the published spec
(github.com/foxglove/ws-protocol, docs/spec.md), independent of the server's own code:
JSON ops in and out, binary Message Data (opcode 0x01, u32 subscription id, u64 receive
time ns, little endian) in, Client Message Data (opcode 0x01, u32 channel id) out."""

from __future__ import annotations

import asyncio
import json
import ssl
import struct
from collections.abc import Callable
from typing import Any

from websockets.asyncio.client import ClientConnection, connect

SUBPROTOCOL = "foxglove.websocket.v1"


def tls() -> ssl.SSLContext:
    context = ssl.create_default_context()
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE  # the test's self-signed certificate
    return context


async def https_get(port: int, path: str, token: str | None = None,
                    secure: bool = True) -> tuple[int, bytes]:
    """One ``GET`` (HTTP/1.1, connection closed by the server): status and body."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port,
                                                   ssl=tls() if secure else None)
    auth = f"Authorization: Bearer {token}\r\n" if token else ""
    writer.write(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{auth}\r\n".encode())
    data = await asyncio.wait_for(reader.read(), 5)
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body


async def ticket(port: int, token: str) -> str:
    status, body = await https_get(port, "/foxglove/ticket", token)
    assert status == 200, body
    value: str = json.loads(body)["ticket"]
    return value


def open_viewer(port: int, ticket_value: str | None, secure: bool = True, **kw: Any) -> Any:
    """Connect like Foxglove does: ``wss://host:port/?ticket=...`` with the subprotocol."""
    scheme = "wss" if secure else "ws"
    query = f"?ticket={ticket_value}" if ticket_value is not None else ""
    return connect(f"{scheme}://127.0.0.1:{port}/{query}", subprotocols=[SUBPROTOCOL],
                   ssl=tls() if secure else None, max_size=None, compression=None, **kw)


class Viewer:
    """What a Foxglove client keeps: channels by id and topic, received messages."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.server_info: dict[str, Any] | None = None
        self.channels: dict[int, dict[str, Any]] = {}
        self.statuses: list[dict[str, Any]] = []
        self.messages: list[tuple[int, int, bytes]] = []  # (subscription, time ns, payload)
        self.ops: list[str] = []

    def channel(self, topic: str) -> dict[str, Any] | None:
        return next((c for c in self.channels.values() if c["topic"] == topic), None)

    def take(self, message: str | bytes) -> None:
        if isinstance(message, bytes):
            assert message[0] == 0x01, message[:1]
            sub_id, stamp = struct.unpack_from("<IQ", message, 1)
            self.messages.append((sub_id, stamp, message[13:]))
            return
        data = json.loads(message)
        self.ops.append(data["op"])
        if data["op"] == "serverInfo":
            self.server_info = data
        elif data["op"] == "advertise":
            self.channels.update({c["id"]: c for c in data["channels"]})
        elif data["op"] == "unadvertise":
            for channel_id in data["channelIds"]:
                self.channels.pop(channel_id, None)
        elif data["op"] == "status":
            self.statuses.append(data)

    async def until(self, predicate: Callable[[], bool], timeout_s: float = 5.0) -> None:
        """Read messages until *predicate* holds (a deadline, not a sleep)."""

        async def scan() -> None:
            while not predicate():
                self.take(await self.ws.recv())

        await asyncio.wait_for(scan(), timeout_s)

    async def subscribe(self, sub_id: int, channel_id: int) -> None:
        await self.ws.send(json.dumps({"op": "subscribe",
                                       "subscriptions": [{"id": sub_id,
                                                          "channelId": channel_id}]}))

    async def advertise(self, channel_id: int, topic: str, schema_name: str) -> None:
        await self.ws.send(json.dumps({"op": "advertise", "channels": [
            {"id": channel_id, "topic": topic, "encoding": "cdr", "schemaName": schema_name}]}))

    async def publish(self, channel_id: int, payload: bytes) -> None:
        await self.ws.send(struct.pack("<BI", 0x01, channel_id) + payload)
