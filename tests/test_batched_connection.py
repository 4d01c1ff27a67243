"""BatchedWritesConnection over a real websockets server on loopback."""

from __future__ import annotations

import asyncio
import os

from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import ServerConnection, serve

from fleetctl.batched_connection import (
    ONE_PASS_MIN_BYTES,
    BatchedWritesConnection,
    server_binary_frame,
)
from fleetctl.linkdeflate import RelayDeflateFactory


class BatchedClient(BatchedWritesConnection, ClientConnection):
    """The client side, as the robot link composes it."""


def test_mixed_batch_arrives_intact_and_in_order() -> None:
    # Small and large binary frames (both serialization paths, joined and direct writes),
    # an unaligned view, and text, in one batch and then a second batch.
    view_backing = os.urandom(ONE_PASS_MIN_BYTES + 11)
    batch: list[bytes | str] = [
        b"small", os.urandom(ONE_PASS_MIN_BYTES), "text", os.urandom(1_000_003),
        os.urandom(ONE_PASS_MIN_BYTES - 1), memoryview(view_backing)[5:],  # type: ignore[list-item]
        b"",
    ]
    expected = [bytes(x) if not isinstance(x, str) else x for x in batch] * 2

    async def main() -> list[bytes | str]:
        got: list[bytes | str] = []
        done = asyncio.Event()

        async def handler(ws: ServerConnection) -> None:
            async for message in ws:
                got.append(message)
                if len(got) == len(expected):
                    done.set()

        async with serve(handler, "127.0.0.1", 0, compression=None, max_size=None) as server:
            port = server.sockets[0].getsockname()[1]
            async with connect(f"ws://127.0.0.1:{port}", compression=None,
                               create_connection=BatchedClient) as ws:
                assert isinstance(ws, BatchedClient)
                await ws.send_frames(batch)
                await ws.send_frames(batch)
                await asyncio.wait_for(done.wait(), 10.0)
        return got

    assert asyncio.run(main()) == expected


def test_ping_pongs_after_large_small_and_no_frames() -> None:
    # A ping after a large (one-pass) frame, after a small one, or alone: each time the
    # server's pong completes the waiter, and every frame arrives intact.
    batches: list[list[bytes | str]] = [[os.urandom(ONE_PASS_MIN_BYTES * 4)], [b"small"], []]

    async def main() -> tuple[list[bytes | str], list[float]]:
        got: list[bytes | str] = []
        both = asyncio.Event()

        async def handler(ws: ServerConnection) -> None:
            async for message in ws:
                got.append(message)
                if len(got) == 2:
                    both.set()

        rtts = []
        async with serve(handler, "127.0.0.1", 0, compression=None, max_size=None) as server:
            port = server.sockets[0].getsockname()[1]
            async with connect(f"ws://127.0.0.1:{port}", compression=None,
                               create_connection=BatchedClient) as ws:
                assert isinstance(ws, BatchedClient)
                for i, batch in enumerate(batches):
                    waiter = await ws.send_frames(batch, ping=i.to_bytes(8, "big"))
                    assert waiter is not None
                    rtts.append(await asyncio.wait_for(waiter, 10.0))
                await asyncio.wait_for(both.wait(), 10.0)
        return got, rtts

    got, rtts = asyncio.run(main())
    assert got == [batches[0][0], b"small"]
    assert len(rtts) == 3 and all(rtt >= 0 for rtt in rtts)


class BatchedServer(BatchedWritesConnection, ServerConnection):
    """The server side, as the relay composes it."""


def test_a_server_frame_is_built_once_for_all_its_receivers() -> None:
    # The relay writes one relayed payload to each receiver in turn: the same frame object
    # serves them all, and each receiver (one without extensions, one that negotiated the
    # inbound-only deflate, as browsers and robots do) reads every message intact, the
    # batch's text and sizes on both sides of 126 and 65536 included.
    payloads = [b"", b"x" * 125, os.urandom(126), os.urandom(70_000), b"last"]
    batch: list[bytes | str] = [payloads[0], "text", *payloads[1:]]
    assert server_binary_frame(payloads[2]) is server_binary_frame(payloads[2])
    other = bytes(payloads[2])  # equal bytes, another object: built anew, same bytes
    assert server_binary_frame(other) == server_binary_frame(payloads[2])
    buffer = bytearray(b"before")  # mutable: never taken from the cache
    assert server_binary_frame(buffer).endswith(b"before")
    buffer[:] = b"after!"
    assert server_binary_frame(buffer).endswith(b"after!")

    async def main() -> list[list[bytes | str]]:
        receivers: list[BatchedServer] = []
        both = asyncio.Event()

        async def handler(ws: ServerConnection) -> None:
            assert isinstance(ws, BatchedServer)
            receivers.append(ws)
            if len(receivers) == 2:
                both.set()
            await ws.wait_closed()

        async def receive(port: int, **kwargs: object) -> list[bytes | str]:
            async with connect(f"ws://127.0.0.1:{port}", max_size=None,
                               **kwargs) as ws:  # type: ignore[arg-type]
                await asyncio.wait_for(both.wait(), 10.0)
                return [await asyncio.wait_for(ws.recv(), 10.0) for _ in batch]

        async with serve(handler, "127.0.0.1", 0, compression=None, max_size=None,
                         extensions=[RelayDeflateFactory()],
                         create_connection=BatchedServer) as server:
            port = server.sockets[0].getsockname()[1]
            tasks = [asyncio.create_task(receive(port, compression=None)),
                     asyncio.create_task(receive(port, compression="deflate"))]
            await asyncio.wait_for(both.wait(), 10.0)
            assert sorted(len(r.protocol.extensions) for r in receivers) == [0, 1]
            for ws in receivers:
                assert ws.can_write_now()
                ws.write_frames_now(batch)
            return list(await asyncio.gather(*tasks))

    assert asyncio.run(main()) == [batch, batch]
