"""Tests of fleetctl.wire.whole_messages against a real websockets server on loopback."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator, Sequence

import pytest
from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosedError

from fleetctl.wire.fragments import Reassembler, split
from fleetctl.wire.whole_messages import first_whole_messages, whole_messages
from tests.support import string_frame

EVENT = json.dumps({"type": "subscribed", "pattern": ".*"})
DEADLINE_S = 10.0


def fragmented(topic: str, text: str, message_id: int = 1) -> tuple[bytes, list[bytes]]:
    """A String frame on *topic* of *text* and its fragments (at least three)."""
    frame = string_frame(topic, text)
    parts = split(frame, topic=topic, message_id=message_id, max_fragment_bytes=1000,
                  no_drop=False)
    assert len(parts) >= 3
    return frame, parts


@contextlib.asynccontextmanager
async def relay_sending(script: Sequence[str | bytes], *,
                        abort: bool = False) -> AsyncIterator[str]:
    """A server on loopback that sends *script* to whoever connects, then closes (a normal
    close, or the TCP connection dropped with no close frame when *abort*); its URL."""

    async def handler(ws: ServerConnection) -> None:
        for frame in script:
            await ws.send(frame)
        if abort:
            ws.transport.abort()
        else:
            await ws.close()

    async with serve(handler, "127.0.0.1", 0) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        yield f"ws://127.0.0.1:{port}/"


async def received(script: Sequence[str | bytes],
                   reassembler: Reassembler | None = None) -> list[bytes]:
    """Every whole message a client gets from a server sending *script*."""
    async with relay_sending(script) as url, connect(url, max_size=None) as ws:
        async with asyncio.timeout(DEADLINE_S):
            return [whole async for whole in whole_messages(ws, reassembler)]


async def test_fragments_in_order_come_out_whole_between_plain_frames() -> None:
    big, parts = fragmented("/r1/map", "m" * 5000)
    small, last = string_frame("/r1/pose", "p"), string_frame("/r1/pose", "q")
    assert await received([EVENT, small, *parts, EVENT, last]) == [small, big, last]


async def test_interleaved_topics_complete_each_in_its_turn() -> None:
    a, a_parts = fragmented("/r1/a", "a" * 4000)
    b, b_parts = fragmented("/r1/b", "b" * 6000)
    assert len(b_parts) > len(a_parts)
    interleaved = [f for pair in zip(a_parts, b_parts, strict=False) for f in pair]
    interleaved += b_parts[len(a_parts):]
    assert await received(interleaved) == [a, b]


async def test_text_frames_alone_give_nothing() -> None:
    assert await received([EVENT, EVENT]) == []


async def test_a_close_mid_message_ends_the_stream_and_keeps_the_partial() -> None:
    done = string_frame("/r1/pose", "p")
    _, parts = fragmented("/r1/map", "m" * 5000)
    reassembler = Reassembler(1 << 20, 10.0)
    assert await received([done, *parts[:-1]], reassembler) == [done]
    assert reassembler.pending_messages == 1
    assert reassembler.stats.completed == 0


async def test_drops_are_counted_in_the_reassembler_given() -> None:
    _, old = fragmented("/r1/map", "o" * 5000, message_id=1)
    new, new_parts = fragmented("/r1/map", "n" * 5000, message_id=2)
    reassembler = Reassembler(1 << 20, 10.0)
    assert await received([*old[:2], *new_parts], reassembler) == [new]
    assert reassembler.stats.superseded == 1


async def test_an_abnormal_close_is_raised_not_taken_for_the_end() -> None:
    async with relay_sending([string_frame("/r1/pose")], abort=True) as url, \
            connect(url) as ws, asyncio.timeout(DEADLINE_S):
        with pytest.raises(ConnectionClosedError):
            async for _ in whole_messages(ws):
                pass


async def test_first_whole_messages_takes_count_and_leaves_the_rest() -> None:
    big, parts = fragmented("/r1/map", "m" * 5000)
    small = string_frame("/r1/pose")
    script: list[str | bytes] = [EVENT, *parts, small, string_frame("/r1/pose", "later")]
    async with relay_sending(script) as url, connect(url) as ws, asyncio.timeout(DEADLINE_S):
        assert await first_whole_messages(ws, 2) == [big, small]
        assert await ws.recv() == script[-1]  # the next frame is still the connection's


async def test_first_whole_messages_says_how_many_came_before_the_end() -> None:
    _, parts = fragmented("/r1/map", "m" * 5000)
    async with relay_sending([string_frame("/r1/pose"), *parts[:-1]]) as url, \
            connect(url) as ws, asyncio.timeout(DEADLINE_S):
        with pytest.raises(EOFError, match="after 1 of 2 whole messages"):
            await first_whole_messages(ws, 2)


async def test_first_whole_messages_refuses_a_count_below_one() -> None:
    async def nothing() -> AsyncIterator[str | bytes]:
        return
        yield b""

    with pytest.raises(ValueError, match="at least 1, not 0"):
        await first_whole_messages(nothing(), 0)
