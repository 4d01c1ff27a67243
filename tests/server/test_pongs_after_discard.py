"""No pong after frames the relay discarded, whichever close made it stop taking them.

A pong tells a client that everything it sent before the ping was taken: the robot's
link forgets its no_drop messages on it (docs/security.md, "A pong acknowledges only
frames the relay took"). Once the relay decides to close a connection it discards what
still comes from it, but until its close frame was written websockets went on answering
pings: a revoked token (4403), a session taken over (4409), too many malformed frames
(1007) or a message in too many frames (1009) answered the ping that followed frames the
relay had dropped, and a client that trusted it lost them. Each test sends no_drop
frames and a ping into such a close through a real relay and a hand-written client, and
asserts that no pong follows frames the relay did not take (``messages_in``).
"""

from __future__ import annotations

import asyncio
import copy
import fcntl
import json
import os
import socket
import struct
import termios
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerConfig, ServerLimits
from fleetctl.server.connection import MAX_MESSAGE_FRAMES, RelayConnection
from fleetctl.server.sessions import SESSION_HEADER
from fleetctl.wire.control import encode_subscription
from tests.security.conftest import RawClient, frame_head
from tests.server.conftest import ALICE_TOKEN, AUTH, client, wait_for
from tests.support import string_frame

PING, PONG, CLOSE, TEXT, BINARY, CONT = 0x9, 0xA, 0x8, 0x1, 0x2, 0x0
EVENTS = "/husky1/events"  # alice may send anywhere


def frame(opcode: int, payload: bytes, fin: bool = True) -> bytes:
    """A client frame with a zero masking key (legal, RFC 6455 5.3)."""
    return frame_head(opcode, len(payload), fin) + b"\0\0\0\0" + payload


def events(first: int, last: int) -> bytes:
    """no_drop frames e<first>..e<last> on :data:`EVENTS`, as one write."""
    return b"".join(frame(BINARY, string_frame(EVENTS, f"e{n}", no_drop=True, seq=n))
                    for n in range(first, last + 1))


def taken(srv: RelayServer) -> int:
    """Frames on :data:`EVENTS` the relay took (relayed, counted in)."""
    return srv.metrics.messages_in.get(EVENTS, 0)


async def opened(srv: RelayServer, headers: bytes = b"", *, small_window: bool = False,
                 ) -> RawClient:
    """A raw client with ALICE_TOKEN (and *headers*), past its welcome."""
    if small_window:  # what it does not read stays on the relay's side
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # before connect
        sock.setblocking(False)
        await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", srv.port))
        raw = RawClient(*await asyncio.open_connection(sock=sock, limit=4096))
    else:
        raw = await RawClient.open(srv.port)
    auth = f"Authorization: Bearer {ALICE_TOKEN}\r\n".encode()
    assert await raw.request(auth + headers) == 101
    await text_of_type(raw, "welcome")
    return raw


async def text_of_type(raw: RawClient, kind: str) -> dict[str, Any]:
    while (got := await raw.next_frame()) is not None:
        if got[0] == TEXT and (data := json.loads(got[1])).get("type") == kind:
            return dict(data)
    raise AssertionError(f"closed before a {kind!r} frame")


async def pongs_and_close(raw: RawClient) -> tuple[list[bytes], int | None]:
    """Read to the close frame: the pongs before it, and its code. After its close frame
    nothing a client reads counts (RFC 6455 1.4), so neither do pongs after it."""
    pongs: list[bytes] = []
    while (got := await raw.next_frame()) is not None:
        opcode, payload = got
        if opcode == PONG:
            pongs.append(payload)
        elif opcode == CLOSE:
            raw.writer.write(frame(CLOSE, payload[:2]))  # as a client answers it
            return pongs, struct.unpack("!H", payload[:2])[0] if payload else None
    return pongs, None


def relay_side(srv: RelayServer, name: str) -> list[RelayConnection]:
    """The relay's connections of identity *name*, oldest first."""
    assert srv._server is not None
    found = [c for c in srv._server.connections
             if isinstance(c, RelayConnection) and c.relay_state is not None
             and name in c.relay_state.peer.identity_names]
    return sorted(found, key=lambda c: c.relay_state.peer.peer_id)


def unread(connection: RelayConnection) -> int:
    """Bytes in the relay's socket of *connection* that it has not read yet."""
    sock = connection.transport.get_extra_info("socket")
    got = fcntl.ioctl(sock.fileno(), termios.FIONREAD, b"\0\0\0\0")
    return int(struct.unpack("i", got)[0])


def arrived(connection: RelayConnection, nbytes: int, timeout_s: float = 5.0) -> None:
    """Wait, without letting the loop run (so the relay cannot read them), until *nbytes*
    wait in *connection*'s socket: loopback delivers them within the writer's send."""
    deadline = time.monotonic() + timeout_s
    while unread(connection) < nbytes:
        assert time.monotonic() < deadline, "the bytes did not arrive"


def write_auth(path: Path, raw: dict[str, Any]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(yaml.safe_dump(raw))
    os.replace(tmp, path)


@pytest.fixture
async def live(tmp_path: Path) -> AsyncIterator[tuple[RelayServer, Path]]:
    """A relay reading its auth map from a file (reloaded by the tests)."""
    path = tmp_path / "auth.yaml"
    write_auth(path, AUTH)
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=path,
                          database=tmp_path / "fleet.db")
    async with RelayServer(config) as srv:
        srv.reloader.poll_interval_s = 3600.0  # only the test reloads
        yield srv, path


async def test_frames_after_a_revocation_get_no_pong(
    live: tuple[RelayServer, Path],
) -> None:
    """The robot's frames and ping are in the relay's socket when the auth map without
    its token is reloaded: the relay discards the frames (the connection is closing
    with 4403) and must not answer the ping."""
    srv, path = live
    raw = await opened(srv)
    raw.writer.write(events(1, 3) + frame(PING, b"before"))
    pongs_before = await pongs_until(raw, b"before")
    assert pongs_before and taken(srv) == 3  # an ordinary ack while the token holds
    [relay] = relay_side(srv, "alice")
    late = events(4, 8) + frame(PING, b"after")
    raw.writer.write(late)
    arrived(relay, len(late))
    without_alice = copy.deepcopy(AUTH)
    without_alice["identities"] = [i for i in AUTH["identities"] if i["name"] != "alice"]
    write_auth(path, without_alice)
    assert srv.reload_auth("test")  # revoked while its frames wait to be read
    pongs, code = await asyncio.wait_for(pongs_and_close(raw), 10)
    assert code == 4403
    assert taken(srv) == 3  # e4..e8 came after the revocation: discarded
    assert b"after" not in pongs  # a pong would say e4..e8 were taken
    raw.close()


async def pongs_until(raw: RawClient, last: bytes) -> list[bytes]:
    pongs: list[bytes] = []
    while (got := await raw.next_frame()) is not None:
        if got[0] == PONG:
            pongs.append(got[1])
            if got[1] == last:
                return pongs
    raise AssertionError("closed before the pong")


async def test_frames_after_malformed_ones_closing_the_connection_get_no_pong(
    make_server: Callable[..., RelayServer],
) -> None:
    """Frames past the malformed frame that closes the connection (1007) are discarded;
    the ping after them, read in the same socket read, must not be answered."""
    limits = ServerLimits(max_malformed_in_row=3)
    async with make_server(limits=limits) as srv:
        raw = await opened(srv)
        raw.writer.write(events(1, 2) + frame(BINARY, b"\x01\x02") * 3 + events(3, 5)
                         + frame(PING, b"after"))
        pongs, code = await asyncio.wait_for(pongs_and_close(raw), 10)
        assert code == 1007
        assert taken(srv) == 2  # e1, e2; e3..e5 came after the close was decided
        assert b"after" not in pongs
        raw.close()


async def test_a_message_refused_for_its_frame_count_gets_no_pong(
    server: RelayServer,
) -> None:
    """A message in more than MAX_MESSAGE_FRAMES frames is refused (1009) and the ping
    read after it must not be answered: it would say the message was taken."""
    raw = await opened(server)
    refused = (frame(BINARY, string_frame(EVENTS, "big", no_drop=True), fin=False)
               + frame(CONT, b"", fin=False) * (MAX_MESSAGE_FRAMES - 1)
               + frame(CONT, b""))
    raw.writer.write(events(1, 2) + refused + frame(PING, b"after"))
    pongs, code = await asyncio.wait_for(pongs_and_close(raw), 10)
    assert code == 1009
    assert taken(server) == 2
    assert b"after" not in pongs
    raw.close()


async def test_an_oversized_frame_ends_the_reading_before_any_later_ping(
    make_server: Callable[..., RelayServer],
) -> None:
    """Guard: a frame over max_frame_bytes fails the connection (1009) in websockets'
    parser, which reads nothing after it. A pong of the ping before it may come (what
    preceded it was taken); none of the ping after it. Fails if the relay ever drops an
    oversized frame and reads on (its own size check in the sink, say) while websockets
    answers the later ping."""
    async with make_server(limits=ServerLimits(max_frame_bytes=4096)) as srv:
        raw = await opened(srv)
        raw.writer.write(events(1, 2) + frame(PING, b"first") + frame(BINARY, b"x" * 5000)
                         + events(3, 4) + frame(PING, b"after"))
        pongs, code = await asyncio.wait_for(pongs_and_close(raw), 10)
        assert code == 1009
        assert taken(srv) == 2
        assert b"after" not in pongs
        raw.close()


async def test_frames_after_a_session_takeover_get_no_pong(
    server: RelayServer, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The taken-over connection's close waits for its queued frames to be written (a
    robot behind a slow downlink): meanwhile the relay discards what it sends, and the
    pong it held while the robot did not read went out when it read again, before the
    close frame. Here the robot reads only once its frames and ping were read."""
    # The wait is bounded (ABORT_AFTER_S); longer here, so that a slow test host does
    # not close the connection before the robot reads (the pong would then come after
    # the close frame, where it does not count, and the test pass without the fix).
    monkeypatch.setattr("fleetctl.server.app.ABORT_AFTER_S", 30.0)
    session = f"{SESSION_HEADER}: s1\r\n".encode()
    old = await opened(server, session, small_window=True)
    old.writer.write(frame(BINARY, encode_subscription("/husky1/.*")))
    await text_of_type(old, "subscribed")
    [relay] = relay_side(server, "alice")
    async with client(server, source="127.0.0.2") as robot:  # fills old's write buffer
        for _ in range(100):  # 6 MB at most; a few frames fill it
            if relay.paused:
                break
            await robot.send(string_frame("/husky1/cloud", "x" * 60_000))
            await wait_for(lambda: not robot.transport.get_write_buffer_size(), 5)
        assert relay.paused
        new = await opened(server, session)  # takes the session over
        await wait_for(lambda: relay.relay_state.peer.closing)
        late = events(1, 3) + frame(PING, b"after")
        old.writer.write(late)
        arrived(relay, len(late))
        await wait_for(lambda: unread(relay) == 0)  # read (and discarded)
        pongs, code = await asyncio.wait_for(pongs_and_close(old), 10)
    assert code == 4409
    assert taken(server) == 0
    assert b"after" not in pongs
    old.close()
    new.close()
