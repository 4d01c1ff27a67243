"""Frames a hostile or broken client sends that websockets accepts but that cost the relay
memory outside its bounds: pings it never reads the pongs of, messages cut into endless
continuation frames (docs/security.md, "Limits")."""

from __future__ import annotations

import asyncio
import json
import socket
from collections.abc import Callable
from typing import Any

import pytest

from fleetctl.server.app import RelayServer
from fleetctl.server.connection import MAX_MESSAGE_FRAMES, PRE_AUTH_MAX_MESSAGE_FRAMES
from fleetctl.server.relay import RelayCore
from tests.security.conftest import RawClient, frame_head
from tests.server.conftest import (
    ALICE_TOKEN,
    client,
    next_binary,
    next_json,
    subscribe,
    wait_for,
)
from tests.support import decode_text, string_frame

PING, PONG, CONT, TEXT, BINARY = 0x9, 0xA, 0x0, 0x1, 0x2
PINGS = 40_000  # 5 MB of pongs: more than the kernel buffers of a loopback connection


def frame(opcode: int, payload: bytes, fin: bool = True) -> bytes:
    """A client frame with a zero masking key (legal, RFC 6455 5.3, and cheap to build)."""
    return frame_head(opcode, len(payload), fin) + b"\0\0\0\0" + payload


async def small_window_client(port: int, source: str) -> RawClient:
    """A raw client whose kernel receive buffer is tiny, so that what it does not read
    stays on the server's side."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # before connect: no autotune
    sock.setblocking(False)
    sock.bind((source, 0))
    await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
    reader, writer = await asyncio.open_connection(sock=sock, limit=4096)
    return RawClient(reader, writer)


async def pongs_until(raw: RawClient, last: bytes) -> int:
    """Read until the pong carrying *last*; return how many pongs came."""
    count = 0
    while (got := await raw.next_frame()) is not None:
        opcode, payload = got
        count += opcode == PONG
        if opcode == PONG and payload == last:
            return count
    raise AssertionError("the server hung up before answering the last ping")


def ping_flood() -> tuple[bytes, bytes]:
    """*PINGS* pings of 125 bytes, and the payload of the last one."""
    last = b"last".ljust(125, b".")
    body = b"".join(frame(PING, b"%0125d" % i) for i in range(PINGS - 1))
    return body + frame(PING, last), last


async def test_pings_of_a_client_that_does_not_read_cost_one_pong(
    server: RelayServer,
) -> None:
    raw = await small_window_client(server.port, "127.0.0.1")
    assert await raw.request(f"Authorization: Bearer {ALICE_TOKEN}\r\n".encode()) == 101
    flood, last = ping_flood()
    raw.writer.write(flood)  # the server reads all of it (authenticated: a robot's rate)
    await wait_for(lambda: server.metrics.pongs_coalesced > PINGS // 2, 20)
    # Without the bound every ping's pong waited in the relay's write buffer (5 MB here);
    # now what the kernel took, then the latest pong, which still answers the last ping.
    pongs = await asyncio.wait_for(pongs_until(raw, last), 20)
    assert pongs < PINGS // 4
    assert pongs + server.metrics.pongs_coalesced >= PINGS - 1
    assert "fleetctl_pongs_coalesced_total" in server.metrics.render()
    raw.close()


async def test_an_unauthenticated_ping_flood_costs_one_held_pong(
    server: RelayServer,
) -> None:
    """Before its token a connection's pings are not answered (its frames may yet be
    discarded: a pong would say they were taken): the latest pong is held, one frame
    whatever the flood, and sent once the token is accepted. Before, every pong went
    into the write buffer of a client that did not read (5 MB here), which then had to
    stop reading it."""
    raw = await small_window_client(server.port, "127.0.0.9")  # no identity
    assert await raw.request() == 101
    flood, last = ping_flood()
    raw.writer.write(flood)
    assert server._server is not None
    connections = server._server.connections
    await wait_for(lambda: server.metrics.pongs_coalesced >= PINGS - 1, 20)  # all read
    assert all(c.transport.get_write_buffer_size() == 0 for c in connections)
    raw.writer.write(frame(TEXT, json.dumps({"token": ALICE_TOKEN}).encode()))
    assert await asyncio.wait_for(pongs_until(raw, last), 20) == 1  # the last one only
    while (got := await raw.next_frame()) is not None and got[0] != TEXT:
        pass
    assert got is not None and json.loads(got[1])["type"] == "welcome"
    raw.close()


async def test_a_message_in_too_many_continuation_frames_is_refused(
    server: RelayServer,
) -> None:
    # Empty continuation frames cost nothing against max_size, ~100 bytes each in the
    # relay while it assembles the message.
    raw = await RawClient.open(server.port, source="127.0.0.9")  # no identity
    assert await raw.request() == 101
    raw.writer.write(frame(BINARY, b"", fin=False)
                     + frame(CONT, b"", fin=False) * PRE_AUTH_MAX_MESSAGE_FRAMES)
    assert await raw.close_code() == 1009
    assert await raw.reader.read() == b""  # cut: a peer sending this goes on sending
    raw.close()

    raw = await RawClient.open(server.port, source="127.0.0.9")
    assert await raw.request(f"Authorization: Bearer {ALICE_TOKEN}\r\n".encode()) == 101
    raw.writer.write(frame(BINARY, b"", fin=False)
                     + frame(CONT, b"", fin=False) * MAX_MESSAGE_FRAMES)
    assert await raw.close_code() == 1009
    raw.close()
    await wait_for(lambda: server.metrics.closes.get(1009) == 2)
    await wait_for(lambda: not server.core.peers and server.gate.open == 0)


async def test_a_message_in_many_frames_within_the_bound_is_relayed(
    make_server: Callable[..., RelayServer],
) -> None:
    async with make_server() as srv, client(srv, token=ALICE_TOKEN) as viewer:
        assert (await subscribe(viewer, "/husky1/chat"))["type"] == "subscribed"
        raw = await RawClient.open(srv.port, source="127.0.0.2")  # husky1
        assert await raw.request() == 101
        message = string_frame("/husky1/chat", "x" * 3000)
        parts = [message[i:i + 1] for i in range(MAX_MESSAGE_FRAMES - 1)]
        parts.append(message[MAX_MESSAGE_FRAMES - 1:])
        raw.writer.write(frame(BINARY, parts[0], fin=False)
                         + b"".join(frame(CONT, p, fin=False) for p in parts[1:-1])
                         + frame(CONT, parts[-1]))
        assert decode_text(await next_binary(viewer)) == "x" * 3000
        raw.close()


async def test_a_client_closed_for_bad_input_is_not_read_any_further(
    server: RelayServer,
) -> None:
    # A client that goes on sending after the server's close frame (and never answers
    # it) used to be read, every frame parsed, through websockets' 10 s close timeout.
    garbage = frame(BINARY, b"\0" * 40)
    raw = await RawClient.open(server.port, source="127.0.0.9")  # no identity
    assert await raw.request() == 101
    raw.writer.write(garbage * 100)
    assert await raw.close_code() == 4403
    assert await asyncio.wait_for(raw.reader.read(), 3) == b""  # cut, not waited on
    raw.close()

    raw = await RawClient.open(server.port, source="127.0.0.9")
    assert await raw.request(f"Authorization: Bearer {ALICE_TOKEN}\r\n".encode()) == 101
    in_a_row = server.config.limits.max_malformed_in_row
    raw.writer.write(garbage * (in_a_row + 100))
    assert await raw.close_code() == 1007
    assert await asyncio.wait_for(raw.reader.read(), 3) == b""
    raw.close()
    await wait_for(lambda: not server.core.peers and server.gate.open == 0)


async def test_a_frame_that_trips_a_bug_costs_the_frame_not_the_connection(
    server: RelayServer, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
) -> None:
    # Complete binary frames are handled inside data_received: an exception there made
    # asyncio drop the connection ("protocol.data_received() call failed").
    real = RelayCore._note_robot

    def buggy(self: RelayCore, peer: Any, topic: str, type_name: str, frame: bytes) -> None:
        if topic == "/husky1/boom":
            raise ValueError("a bug")
        real(self, peer, topic, type_name, frame)

    monkeypatch.setattr(RelayCore, "_note_robot", buggy)
    async with client(server, token=ALICE_TOKEN) as viewer, \
            client(server, source="127.0.0.2") as robot:
        assert (await subscribe(viewer, "/husky1/chat"))["type"] == "subscribed"
        await robot.send(string_frame("/husky1/boom", "x"))
        error = await next_json(robot, "error")
        assert error["code"] == "malformed_frame" and "ValueError" in error["message"]
        await robot.send(string_frame("/husky1/chat", "still here"))
        assert decode_text(await next_binary(viewer)) == "still here"
    traced = [r.getMessage() for r in caplog.records if r.exc_info]
    assert len(traced) == 1 and traced[0].endswith("[husky1@127.0.0.2]: frame not handled")
