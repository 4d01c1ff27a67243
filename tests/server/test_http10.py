"""HTTP/1.0 requests: a load balancer's health check gets its answer (raw sockets to a
real relay), and a WebSocket upgrade still needs HTTP/1.1."""

from __future__ import annotations

import asyncio

from websockets.http11 import MAX_LINE_LENGTH

from fleetctl.server.app import RelayServer
from fleetctl.server.http10 import RequestLine


async def exchange(port: int, *parts: bytes) -> tuple[str, dict[str, str], bytes]:
    """Send *parts* (each written and drained on its own), read until the server
    closes; return the status line, the headers and the body."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    for part in parts:
        writer.write(part)
        await writer.drain()
    data = await asyncio.wait_for(reader.read(), 5)
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    status, *lines = head.decode().split("\r\n")
    headers = dict(line.split(": ", 1) for line in lines)
    return status, headers, body


async def test_healthz_over_http10(server: RelayServer) -> None:
    status, headers, body = await exchange(server.port, b"GET /healthz HTTP/1.0\r\n\r\n")
    assert status == "HTTP/1.1 200 OK" and body == b"ok\n"
    assert headers["Connection"] == "close" and headers["Content-Length"] == "3"


async def test_healthz_over_http10_split_request_line(server: RelayServer) -> None:
    status, _, body = await exchange(server.port, b"GET /heal", b"thz HTTP/1", b".0\r",
                                     b"\nUser-Agent: lb\r\n\r\n")
    assert status == "HTTP/1.1 200 OK" and body == b"ok\n"


async def test_other_plain_gets_over_http10(server: RelayServer) -> None:
    status, _, body = await exchange(server.port, b"GET /metrics HTTP/1.0\r\n\r\n")
    assert status == "HTTP/1.1 200 OK" and b"fleetctl_connections_total" in body
    status, _, _ = await exchange(server.port, b"GET /nowhere HTTP/1.0\r\n\r\n")
    assert status == "HTTP/1.1 404 Not Found"


async def test_websocket_upgrade_over_http10_is_refused(server: RelayServer) -> None:
    status, _, body = await exchange(
        server.port, b"GET / HTTP/1.0\r\nHost: x\r\nUpgrade: websocket\r\n"
        b"Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
        b"Sec-WebSocket-Version: 13\r\n\r\n")
    assert status == "HTTP/1.1 400 Bad Request" and b"HTTP/1.1" in body
    assert not server.core.peers


def test_request_line_is_held_until_complete_then_rewritten() -> None:
    line = RequestLine()
    assert line.feed(b"GET /healthz HTTP/1.0") == b""
    assert line.feed(b"\r\nHost: x\r\n") == b"GET /healthz HTTP/1.1\r\nHost: x\r\n"
    assert line.http10 and line.done
    assert line.feed(b"\r\n") == b"\r\n"  # after the line: as is

    same = RequestLine()
    request = b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"
    assert same.feed(request) == request and not same.http10

    other = RequestLine()  # only the request line's version is touched
    assert other.feed(b"GET /HTTP/1.0 HTTP/1.1\r\nX: HTTP/1.0\r\n") == \
        b"GET /HTTP/1.0 HTTP/1.1\r\nX: HTTP/1.0\r\n"

    long = RequestLine()  # past websockets' line limit: handed on for it to refuse
    assert long.feed(b"G" * MAX_LINE_LENGTH) == b""
    assert long.feed(b"G") == b"G" * (MAX_LINE_LENGTH + 1) and long.done
