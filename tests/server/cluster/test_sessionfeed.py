"""The per-session stream feed on its own: what it queues, the cursor it derives from the
connection's acknowledgements, and its back-pressure (stream messages stood in for)."""

from __future__ import annotations

import asyncio
import datetime
from dataclasses import dataclass, field

from fleetctl.server.cluster.sessionfeed import SessionFeed
from fleetctl.server.outbound import OutboundScheduler
from tests.support import string_frame, wait_until


@dataclass
class _Seq:
    stream: int


@dataclass
class _Meta:
    sequence: _Seq
    timestamp: datetime.datetime = field(
        default_factory=lambda: datetime.datetime.now(datetime.UTC))


class StreamMsg:
    """What the feed reads of a JetStream message: its data, stream sequence and the time
    the stream stored it."""

    def __init__(self, seq: int, data: bytes, stored_s: float | None = None) -> None:
        self.data = data
        self.metadata = _Meta(_Seq(seq)) if stored_s is None else _Meta(
            _Seq(seq), datetime.datetime.fromtimestamp(stored_s, datetime.UTC))


def feed_for(outbound: OutboundScheduler, wanted: set[str], cursor: int | None = None,
             malformed: list[int] | None = None, since: float = 0.0) -> SessionFeed:
    outbound.track_acks()
    return SessionFeed(outbound, wanted.__contains__, lambda: True, cursor, since,
                       lambda: (malformed if malformed is not None else []).append(1))


def ack_everything_sent(outbound: OutboundScheduler) -> None:
    while outbound.pop() is not None:
        pass
    mark = outbound.ack_mark()
    if mark is not None:
        outbound.acked(mark)


async def test_cursor_follows_acknowledgements_not_queueing() -> None:
    outbound = OutboundScheduler(1 << 20, 100)
    feed = feed_for(outbound, {"/e"})
    for seq in (1, 2, 3):
        await feed._on_msg(StreamMsg(seq, string_frame("/e", f"e{seq}", no_drop=True)))  # type: ignore[arg-type]
    assert outbound.no_drop_queued == 3 and feed.settle() is None  # queued, not acked
    outbound.pop()
    outbound.pop()
    mark = outbound.ack_mark()
    assert mark is not None
    outbound.acked(mark)
    assert feed.settle() == 2  # the third was never acknowledged: replayed next time


async def test_frames_for_others_move_the_cursor_only_behind_acknowledged_ones() -> None:
    outbound = OutboundScheduler(1 << 20, 100)
    feed = feed_for(outbound, {"/e"}, cursor=10)
    await feed._on_msg(StreamMsg(11, string_frame("/e", "mine", no_drop=True)))  # type: ignore[arg-type]
    await feed._on_msg(StreamMsg(12, string_frame("/other", "not mine", no_drop=True)))  # type: ignore[arg-type]
    assert feed.settle() == 10  # 11 is not acknowledged: 12 must not be skipped past it
    ack_everything_sent(outbound)
    await feed._on_msg(StreamMsg(13, string_frame("/other", "x", no_drop=True)))  # type: ignore[arg-type]
    assert feed.settle() == 13


async def test_repeats_after_a_consumer_restart_and_malformed_messages_are_skipped() -> None:
    outbound = OutboundScheduler(1 << 20, 100)
    malformed: list[int] = []
    feed = feed_for(outbound, {"/e"}, malformed=malformed)
    frame = string_frame("/e", "once", no_drop=True)
    await feed._on_msg(StreamMsg(5, frame))  # type: ignore[arg-type]
    await feed._on_msg(StreamMsg(5, frame))  # type: ignore[arg-type]
    await feed._on_msg(StreamMsg(4, frame))  # type: ignore[arg-type]
    await feed._on_msg(StreamMsg(6, b"\x00garbage"))  # type: ignore[arg-type]
    assert outbound.no_drop_queued == 1 and feed.delivered == 1 and malformed == [1]


async def test_a_full_connection_makes_the_feed_wait_instead_of_dropping() -> None:
    outbound = OutboundScheduler(1 << 20, 4)  # half full at 2
    feed = feed_for(outbound, {"/e"})
    for seq in (1, 2):
        await feed._on_msg(StreamMsg(seq, string_frame("/e", str(seq), no_drop=True)))  # type: ignore[arg-type]
    third = asyncio.create_task(feed._on_msg(
        StreamMsg(3, string_frame("/e", "3", no_drop=True))))  # type: ignore[arg-type]
    await asyncio.sleep(0.05)  # the task runs; the absence of a push is the check
    assert not third.done() and outbound.no_drop_queued == 2
    outbound.pop()
    await wait_until(third.done, 5.0)
    assert outbound.no_drop_queued == 2 and not outbound.drops


async def test_without_a_cursor_frames_stored_before_the_session_began_are_skipped() -> None:
    outbound = OutboundScheduler(1 << 20, 100)
    feed = feed_for(outbound, {"/e"}, since=1000.0)
    # A re-created consumer may start at sequence 1: older frames are not the session's.
    await feed._on_msg(StreamMsg(1, string_frame("/e", "old", no_drop=True), 999.0))  # type: ignore[arg-type]
    await feed._on_msg(StreamMsg(2, string_frame("/e", "new", no_drop=True), 1000.5))  # type: ignore[arg-type]
    assert outbound.no_drop_queued == 1 and feed.delivered == 1
    ack_everything_sent(outbound)
    assert feed.settle() == 2
