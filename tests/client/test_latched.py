"""The client's kept latched frames: last per topic, bounded bytes, counted evictions."""

from __future__ import annotations

import threading

from fleetctl.client.latched import LatchedFrames


def test_last_frame_per_topic_oldest_first() -> None:
    kept = LatchedFrames[str](max_bytes=100)
    kept.put("/r1/map", "map-spec", b"m1")
    kept.put("/r1/tf_static", "tf-spec", b"t1")
    kept.put("/r1/map", "map-spec", b"m2")  # replaces, and becomes the newest
    assert kept.snapshot() == [("/r1/tf_static", "tf-spec", b"t1"),
                               ("/r1/map", "map-spec", b"m2")]
    assert kept.total_bytes == 4 and "/r1/map" in kept and len(kept) == 2
    assert kept.stats.kept == 3 and kept.stats.evicted == 0


def test_byte_bound_evicts_the_least_recent_topics() -> None:
    kept = LatchedFrames[None](max_bytes=10)
    kept.put("/a", None, b"aaaa")
    kept.put("/b", None, b"bbbb")
    kept.put("/c", None, b"cccc")  # 12 > 10: /a goes
    assert [t for t, _, _ in kept.snapshot()] == ["/b", "/c"]
    assert kept.stats.evicted == 1 and kept.total_bytes == 8


def test_a_frame_larger_than_the_bound_is_not_kept_and_drops_the_older_one() -> None:
    kept = LatchedFrames[None](max_bytes=10)
    kept.put("/map", None, b"small")
    kept.put("/map", None, b"x" * 11)
    # The old frame is stale now: keeping it would re-send an older map after a reconnect.
    assert kept.snapshot() == [] and kept.total_bytes == 0
    assert kept.stats.too_large == 1


def test_forget_and_memoryviews() -> None:
    kept = LatchedFrames[None]()
    view = memoryview(b"abcdef")[1:4]
    kept.put("/x", None, view)
    assert kept.total_bytes == 3 and kept.snapshot()[0][2] is view
    kept.forget("/x")
    kept.forget("/never")
    assert len(kept) == 0 and kept.total_bytes == 0


def test_concurrent_puts_keep_the_byte_count_exact() -> None:
    kept = LatchedFrames[int](max_bytes=1000)

    def worker(n: int) -> None:
        for i in range(2000):
            kept.put(f"/t{(n * 7 + i) % 30}", n, b"x" * (i % 50 + 1))

    threads = [threading.Thread(target=worker, args=(n,)) for n in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert kept.total_bytes == sum(len(f) for _, _, f in kept.snapshot()) <= 1000
