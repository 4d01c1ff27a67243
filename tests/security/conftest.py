"""Fixtures of the security regressions (project issue 14): the live relay of the server
tests, and a raw HTTP/WebSocket client that can send what a library will not."""

from __future__ import annotations

import asyncio
import base64
import os
import struct

from tests.server.conftest import make_server, server  # noqa: F401  (fixtures)


def frame_head(opcode: int, n: int, fin: bool = True) -> bytes:
    """A masked client frame's first bytes, up to its masking key, for an *n*-byte
    payload (RFC 6455 5.2: FIN, opcode, MASK bit and the 7, 16 or 64-bit length)."""
    first = (0x80 if fin else 0) | opcode
    if n < 126:
        return struct.pack("!BB", first, 0x80 | n)
    if n < 65536:
        return struct.pack("!BBH", first, 0x80 | 126, n)
    return struct.pack("!BBQ", first, 0x80 | 127, n)


class RawClient:
    """A hand-written WebSocket client: arbitrary header bytes, frames parsed by hand."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer

    @classmethod
    async def open(cls, port: int, source: str = "127.0.0.1") -> RawClient:
        reader, writer = await asyncio.open_connection("127.0.0.1", port,
                                                       local_addr=(source, 0))
        return cls(reader, writer)

    async def request(self, extra: bytes = b"", *, upgrade: bool = True,
                      path: bytes = b"/", method: bytes = b"GET") -> int:
        """Send a request with *extra* raw header lines; return the response status."""
        key = base64.b64encode(os.urandom(16))
        head = method + b" " + path + b" HTTP/1.1\r\nHost: x\r\n"
        if upgrade:
            head += (b"Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: " + key
                     + b"\r\nSec-WebSocket-Version: 13\r\n")
        self.writer.write(head + extra + b"\r\n")
        status = await asyncio.wait_for(self.reader.readline(), 5)
        while (await asyncio.wait_for(self.reader.readline(), 5)) not in (b"\r\n", b""):
            pass
        return int(status.split()[1]) if status else 0

    async def send_frame(self, opcode: int, payload: bytes, fin: bool = True) -> None:
        """Send one masked frame (RFC 6455 5.2)."""
        mask = os.urandom(4)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.writer.write(frame_head(opcode, len(payload), fin) + mask + masked)
        await self.writer.drain()

    async def next_frame(self) -> tuple[int, bytes] | None:
        """``(opcode, payload)`` of the next frame, ``None`` once the server hung up."""
        head = await asyncio.wait_for(self.reader.read(2), 10)
        if len(head) < 2:
            return None
        n = head[1] & 0x7F
        if n == 126:
            n = struct.unpack("!H", await self.reader.readexactly(2))[0]
        elif n == 127:
            n = struct.unpack("!Q", await self.reader.readexactly(8))[0]
        return head[0] & 0x0F, await self.reader.readexactly(n)

    async def close_code(self) -> int | None:
        """The code of the server's close frame (``None``: closed without one)."""
        while (frame := await self.next_frame()) is not None:
            opcode, payload = frame
            if opcode == 8:
                return int(struct.unpack("!H", payload[:2])[0]) if payload else None
        return None

    def close(self) -> None:
        self.writer.close()
