"""The relay connection's socket: a slow receiver's backlog stays where it can be dropped."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Callable
from pathlib import Path

import pytest

from fleetctl.server.app import RelayServer
from fleetctl.server.connection import (
    READ_BYTES,
    UNSENT_LIMIT_BYTES,
    RelayConnection,
    limit_unsent,
)
from fleetctl.wire.metadata import read_metadata
from tests.server.conftest import BOB_TOKEN, client, subscribe, wait_for
from tests.support import decode_text, string_frame

FRAME_TEXT_BYTES = 60_000
FLOOD_FRAMES = 10_000  # ~1 MB of small frames written at once
SENT = 200  # 12 MB: past any kernel buffer


async def test_a_slow_receiver_gets_the_newest_frames_not_a_kernel_backlog(
    make_server: Callable[..., RelayServer],
) -> None:
    # A viewer that stops reading (a browser busy drawing): without the unsent cap the
    # kernel's send buffer (autotuned to 4 MiB) fills with ~65 frames nothing can replace,
    # and the viewer works through seconds of stale data once it reads again.
    async with make_server() as srv, client(srv, token=BOB_TOKEN) as viewer, \
            client(srv, source="127.0.0.2") as robot:
        await subscribe(viewer, "/husky1/cam")
        viewer.transport.pause_reading()
        blob = "x" * FRAME_TEXT_BYTES
        for i in range(SENT):
            await robot.send(string_frame("/husky1/cam", f"{i}:{blob}"))
        await wait_for(lambda: srv.metrics.messages_in.get("/husky1/cam", 0) == SENT, 20)
        await wait_for(lambda: srv.metrics.drops.get("/husky1/cam", 0) > 0, 20)
        viewer.transport.resume_reading()
        got: list[int] = []
        while not got or got[-1] != SENT - 1:
            frame = await asyncio.wait_for(viewer.recv(), 10)
            if isinstance(frame, bytes) and read_metadata(frame).topic == "/husky1/cam":
                got.append(int(decode_text(frame).partition(":")[0]))
        # A handful, not a backlog: the viewer's own receive buffer (128 KiB at the
        # start), the unsent cap (up to twice: one write may cross it), a write batch in
        # the transport and the scheduler's newest frame: 7 measured, 48 without the cap.
        assert len(got) <= 12, got
        assert srv.metrics.drops["/husky1/cam"] >= SENT - 12


async def test_limit_unsent_sets_the_option_on_tcp_and_skips_other_sockets(
        tmp_path: Path) -> None:
    loop = asyncio.get_running_loop()
    accepted: list[asyncio.BaseTransport] = []

    class Keep(asyncio.Protocol):
        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            accepted.append(transport)

    tcp = await loop.create_server(Keep, "127.0.0.1", 0)
    unix = await loop.create_unix_server(Keep, str(tmp_path / "s"))
    try:
        port = tcp.sockets[0].getsockname()[1]
        clients = [await loop.create_connection(asyncio.Protocol, "127.0.0.1", port),
                   await loop.create_unix_connection(asyncio.Protocol, str(tmp_path / "s"))]
        await wait_for(lambda: len(accepted) == 2)
        by_family = {t.get_extra_info("socket").family: t for t in accepted}
        assert limit_unsent(by_family[socket.AF_INET]) is True
        sock = by_family[socket.AF_INET].get_extra_info("socket")
        assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NOTSENT_LOWAT) \
            == UNSENT_LIMIT_BYTES
        assert limit_unsent(by_family[socket.AF_UNIX]) is False
        for transport, _ in clients:
            transport.close()
    finally:
        tcp.close()
        unix.close()


async def test_a_flooding_sender_is_read_a_slice_at_a_time(
    make_server: Callable[..., RelayServer], monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The frames of one read are relayed before the loop serves another connection: with
    # asyncio's 256 KiB reads a robot sending small frames as fast as it could held the
    # other connections for ~2,400 frames each round (a 200 Hz pair's p50: 160 ms).
    reads: list[int] = []
    real = RelayConnection.data_received

    def data_received(self: RelayConnection, data: bytes) -> None:
        reads.append(len(data))
        real(self, data)

    monkeypatch.setattr(RelayConnection, "data_received", data_received)
    async with make_server() as srv, client(srv, source="127.0.0.2") as robot:
        frame = string_frame("/husky1/chat", "x" * 40)
        robot.transport.write(b"".join(_client_frame(frame) for _ in range(FLOOD_FRAMES)))
        await wait_for(lambda: srv.metrics.messages_in.get("/husky1/chat", 0) == FLOOD_FRAMES,
                       20)
        assert sum(reads) > 4 * READ_BYTES and max(reads) <= READ_BYTES < 256 * 1024


def _client_frame(payload: bytes) -> bytes:
    """A masked binary frame with a zero key (RFC 6455 allows it; nothing to compute)."""
    head = bytes([0x82, 0x80 | 126]) + len(payload).to_bytes(2, "big")
    return head + b"\0\0\0\0" + payload
