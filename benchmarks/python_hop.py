"""The relay's data path in the leanest Python: a measuring probe for
``benchmarks/peer_latency.py --python-hop``, not a relay (issue 19).

The same job as ``benchmarks/compiled_hop`` (its docstring says what is left out), on
asyncio with a bare :class:`asyncio.Protocol`: frames parsed by hand from
``data_received``, unmasked by websockets' C speedup, inflated by zlib, one server frame
built and written to every receiver in the read that brought it. No websockets protocol
object, no relay logic. What it answers: is the Python relay's hop slow because of what
the relay and websockets do per frame (then this probe is much faster than
``fleetctl server``), or because it is Python on asyncio at all (then it is not)?

Usage: ``python benchmarks/python_hop.py HOST:PORT`` (prints ``listening on HOST:PORT``).
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import struct
import sys
import zlib

from websockets.speedups import apply_mask

WS_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
# What the Python relay answers to the robot's offer (fleetctl/linkdeflate.py).
DEFLATE_ANSWER = b"permessage-deflate; server_no_context_takeover; client_max_window_bits=15"
SUBSCRIPTION_TYPE = b"amrl_msgs/msg/RobofleetSubscription"
OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0x2, 0x8, 0x9, 0xA


def server_frame(opcode: int, payload: bytes) -> bytes:
    n = len(payload)
    if n < 126:
        head = bytes((0x80 | opcode, n))
    elif n < 1 << 16:
        head = struct.pack("!BBH", 0x80 | opcode, 126, n)
    else:
        head = struct.pack("!BBQ", 0x80 | opcode, 127, n)
    return head + payload


class Hop(asyncio.Protocol):
    """One connection; *receivers* is shared by all of them."""

    def __init__(self, receivers: list[Hop]) -> None:
        self.receivers = receivers
        self.transport: asyncio.Transport | None = None
        self.buf = bytearray()
        self.upgraded = False
        self.inflater: zlib._Decompress | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def connection_lost(self, exc: Exception | None) -> None:
        if self in self.receivers:
            self.receivers.remove(self)

    def data_received(self, data: bytes) -> None:
        self.buf += data
        if not self.upgraded and not self._upgrade():
            return
        while self._one_frame():
            pass

    def _upgrade(self) -> bool:
        end = self.buf.find(b"\r\n\r\n")
        if end < 0:
            return False
        head = bytes(self.buf[:end]).decode("latin-1")
        del self.buf[:end + 4]
        key, deflate = "", False
        for line in head.split("\r\n")[1:]:
            name, _, value = line.partition(":")
            name = name.strip().lower()
            if name == "sec-websocket-key":
                key = value.strip()
            elif name == "sec-websocket-extensions" and "permessage-deflate" in value:
                deflate = True
        accept = base64.b64encode(hashlib.sha1(key.encode() + WS_GUID).digest())
        answer = (b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\n"
                  b"Connection: Upgrade\r\nSec-WebSocket-Accept: " + accept + b"\r\n")
        if deflate:
            answer += b"Sec-WebSocket-Extensions: " + DEFLATE_ANSWER + b"\r\n"
            self.inflater = zlib.decompressobj(-15)
        assert self.transport is not None
        self.transport.write(answer + b"\r\n")
        self.upgraded = True
        return True

    def _one_frame(self) -> bool:
        """Handle the first whole frame in the buffer; False when there is none. Messages
        in several frames do not occur on this path (fleetctl fragments per message)."""
        buf = self.buf
        if len(buf) < 2:
            return False
        b0, b1 = buf[0], buf[1]
        size, at = b1 & 0x7F, 2
        if size == 126:
            if len(buf) < 4:
                return False
            size, at = struct.unpack_from("!H", buf, 2)[0], 4
        elif size == 127:
            if len(buf) < 10:
                return False
            size, at = struct.unpack_from("!Q", buf, 2)[0], 10
        masked = b1 & 0x80
        if len(buf) < at + (4 if masked else 0) + size:
            return False
        if masked:
            mask = bytes(buf[at:at + 4])
            at += 4
            payload = apply_mask(bytes(buf[at:at + size]), mask)
        else:
            payload = bytes(buf[at:at + size])
        del buf[:at + size]
        assert self.transport is not None
        opcode = b0 & 0x0F
        if opcode == OP_PING:
            self.transport.write(server_frame(OP_PONG, payload))
        elif opcode == OP_CLOSE:
            self.transport.write(server_frame(OP_CLOSE, payload[:2]))
            self.transport.close()
            return False
        elif opcode == OP_BINARY:
            if b0 & 0x40 and self.inflater is not None:
                payload = self.inflater.decompress(payload + b"\x00\x00\xff\xff")
            self._relay(payload)
        return True

    def _relay(self, payload: bytes) -> None:
        if SUBSCRIPTION_TYPE in payload:
            if self not in self.receivers:
                self.receivers.append(self)
            return
        frame = server_frame(OP_BINARY, payload)
        for receiver in self.receivers:
            if receiver is not self and receiver.transport is not None:
                receiver.transport.write(frame)


async def serve(host: str, port: int) -> None:
    receivers: list[Hop] = []
    server = await asyncio.get_running_loop().create_server(lambda: Hop(receivers), host,
                                                            port)
    bound = server.sockets[0].getsockname()
    print(f"listening on {bound[0]}:{bound[1]}", flush=True)
    await server.serve_forever()


def main() -> None:
    host, _, port = (sys.argv[1] if len(sys.argv) > 1 else "127.0.0.1:0").rpartition(":")
    asyncio.run(serve(host, int(port)))


if __name__ == "__main__":
    main()
