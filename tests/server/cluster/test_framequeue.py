"""The bounded frame queue, the subject memo and the recent digests."""

from __future__ import annotations

import asyncio

from fleetctl.server.cluster.framequeue import (
    FrameQueue,
    Queued,
    RecentDigests,
    SubjectMemo,
    frame_digest,
)
from fleetctl.server.cluster.subjects import topic_subject


def entry(frame: bytes, no_drop: bool = False) -> Queued:
    return Queued("s", frame, "/t", no_drop)


def test_bounded_in_frames_and_bytes_and_wakes_its_reader_once() -> None:
    wake = asyncio.Event()
    queue = FrameQueue(max_frames=3, max_bytes=10, wake=wake)
    assert queue.put(entry(b"1234")) and wake.is_set()
    wake.clear()
    assert queue.put(entry(b"5678", True))
    assert not wake.is_set()  # it was not empty
    assert not queue.put(entry(b"abc"))  # 11 bytes
    assert queue.put(entry(b"ab"))
    assert not queue.put(entry(b""))  # 4 frames
    assert [q.frame for q in queue.head(2)] == [b"1234", b"5678"] and len(queue) == 3
    assert queue.keep(lambda q: q.no_drop) == 2
    assert [q.frame for q in queue] == [b"5678"] and queue.bytes == 4
    assert queue.popleft().frame == b"5678" and queue.bytes == 0 and len(queue) == 0


def test_subject_memo_maps_once_per_topic() -> None:
    calls: list[str] = []

    def mapping(root: str, topic: str) -> str:
        calls.append(topic)
        return topic_subject(root, topic)

    memo = SubjectMemo("f", mapping)
    assert memo("/a/b") == memo("/a/b") == "f.a.b"
    assert calls == ["/a/b"]


def test_recent_digests_remember_the_last_ones() -> None:
    recent = RecentDigests(size=2)
    assert recent.first("x") and recent.first("y")
    assert not recent.first("x")
    assert recent.first("z")  # x is forgotten: the oldest of three
    assert recent.first("x")
    assert frame_digest(b"a") == frame_digest(b"a") != frame_digest(b"b")
