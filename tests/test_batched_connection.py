"""BatchedWritesConnection over a real websockets server on loopback."""

from __future__ import annotations

import asyncio
import os

from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import ServerConnection, serve

from fleetctl.batched_connection import ONE_PASS_MIN_BYTES, BatchedWritesConnection


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
