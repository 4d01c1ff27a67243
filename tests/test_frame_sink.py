"""FrameSink over a real websockets server and client on loopback."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import ServerConnection, serve

from fleetctl.frame_sink import FrameSink


class SinkClient(FrameSink, ClientConnection):
    """A client connection with the sink, as the robot link and the e2e consumer have it."""


Script = Callable[[ServerConnection], Awaitable[None]]


async def _with_client(script: Script, body: Callable[[SinkClient], Awaitable[None]]) -> None:
    async def handler(ws: ServerConnection) -> None:
        await ws.recv()  # the client set its sink: frames before that would take recv()
        await script(ws)
        await ws.wait_closed()

    async with serve(handler, "127.0.0.1", 0, compression=None) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        async with connect(f"ws://127.0.0.1:{port}", compression=None,
                           create_connection=SinkClient) as ws:
            assert isinstance(ws, SinkClient)
            await body(ws)


def test_binary_frames_reach_the_sink_without_any_reader() -> None:
    async def script(ws: ServerConnection) -> None:
        for i in range(3):
            await ws.send(bytes([i]) * 10)

    async def body(ws: SinkClient) -> None:
        got: list[bytes] = []
        done = asyncio.Event()

        def sink(frame: bytes) -> bool:
            got.append(frame)
            if len(got) == 3:
                done.set()
            return True

        ws.frame_sink = sink
        await ws.send("go")
        # Nobody calls recv(): the frames are handed over in data_received.
        await asyncio.wait_for(done.wait(), 10.0)
        assert got == [b"\x00" * 10, b"\x01" * 10, b"\x02" * 10]

    asyncio.run(_with_client(script, body))


def test_frames_keep_their_order_behind_a_message_on_the_recv_path() -> None:
    # text, binary, fragmented binary, binary: the text and the fragmented message take
    # recv(); every binary frame after one of them waits behind it until it is handled.
    async def script(ws: ServerConnection) -> None:
        await ws.send("hello")
        await ws.send(b"after-text")
        await ws.send([b"frag", b"mented"])
        await ws.send(b"last")

    async def body(ws: SinkClient) -> None:
        order: list[str] = []
        sunk = asyncio.Event()

        def sink(frame: bytes) -> bool:
            order.append(f"sink:{frame.decode()}")
            sunk.set()
            return True

        ws.frame_sink = sink
        await ws.send("go")
        while len(order) < 4:
            message = await asyncio.wait_for(ws.recv(), 10.0)
            text = message if isinstance(message, str) else message.decode()
            order.append(f"recv:{text}")
            ws.message_handled()
        assert order == ["recv:hello", "recv:after-text", "recv:fragmented", "recv:last"]
        assert not sunk.is_set()
        assert ws.pending_messages == 0

    asyncio.run(_with_client(script, body))


def test_a_declined_frame_takes_the_recv_path() -> None:
    async def script(ws: ServerConnection) -> None:
        await ws.send(b"declined")
        await ws.send(b"kept")

    async def body(ws: SinkClient) -> None:
        taken: list[bytes] = []

        def sink(frame: bytes) -> bool:
            if frame == b"declined":
                return False
            taken.append(frame)
            return True

        ws.frame_sink = sink
        await ws.send("go")
        assert await asyncio.wait_for(ws.recv(), 10.0) == b"declined"
        assert taken == []  # queued behind the declined one until it is handled
        ws.message_handled()
        assert await asyncio.wait_for(ws.recv(), 10.0) == b"kept"

    asyncio.run(_with_client(script, body))
