from __future__ import annotations

from fleetctl.server.outbound import CONTROL_TOPIC, OutboundScheduler


def drain(s: OutboundScheduler) -> list[tuple[str, bytes | str]]:
    out = []
    while (item := s.pop()) is not None:
        out.append(item)
    return out


def test_latest_value_per_droppable_topic_counts_drops() -> None:
    s = OutboundScheduler(10_000, 10)
    for i in range(5):
        s.push("/a", b"a%d" % i, no_drop=False)
    s.push("/b", b"b0", no_drop=False)
    assert drain(s) == [("/a", b"a4"), ("/b", b"b0")]
    assert s.drops == {"/a": 4} and s.queued_bytes == 0 and len(s) == 0


def test_order_control_then_no_drop_fifo_then_latest() -> None:
    s = OutboundScheduler(10_000, 10)
    s.push("/x", b"x", no_drop=False)
    s.push("/e", b"e1", no_drop=True)
    s.push("/e", b"e2", no_drop=True)
    s.push_control("hello")
    assert drain(s) == [(CONTROL_TOPIC, "hello"), ("/e", b"e1"), ("/e", b"e2"), ("/x", b"x")]


def test_no_drop_fifo_bound_drops_newest() -> None:
    s = OutboundScheduler(10_000, 3)
    for i in range(5):
        s.push("/e", b"%d" % i, no_drop=True)
    assert [f for _, f in drain(s)] == [b"0", b"1", b"2"]
    assert s.drops == {"/e": 2}


def test_byte_bound_holds_but_an_empty_queue_takes_one_big_frame() -> None:
    s = OutboundScheduler(100, 1000)
    assert s.push("/big", b"x" * 500, no_drop=False)  # empty: accepted though > bound
    assert not s.push("/other", b"y" * 10, no_drop=False)
    assert not s.push("/e", b"z", no_drop=True)
    assert s.queued_bytes == 500 and s.dropped_total == 2
    drain(s)
    for i in range(50):
        s.push(f"/t{i}", b"q" * 10, no_drop=False)
    assert s.queued_bytes <= 100 and s.dropped_total == 2 + 40


def test_fragments_of_latest_message_kept_and_superseded_partial_dropped_whole() -> None:
    s = OutboundScheduler(10_000, 10)
    s.push("/pc", b"m1f0", no_drop=False, message_id=1)
    s.push("/pc", b"m1f1", no_drop=False, message_id=1)
    s.push("/small", b"s", no_drop=False)
    s.push("/pc", b"m1f2", no_drop=False, message_id=1)
    # Interleaving: one fragment, then the next topic.
    assert s.pop() == ("/pc", b"m1f0")
    assert s.pop() == ("/small", b"s")
    # A new message supersedes the rest of message 1 (dropped whole: counted once).
    s.push("/pc", b"m2f0", no_drop=False, message_id=2)
    s.push("/pc", b"m2f1", no_drop=False, message_id=2)
    assert drain(s) == [("/pc", b"m2f0"), ("/pc", b"m2f1")]
    assert s.drops == {"/pc": 1}
    # Fragments continue a message whose earlier fragments were already sent.
    s.push("/pc", b"m3f0", no_drop=False, message_id=3)
    assert s.pop() == ("/pc", b"m3f0")
    s.push("/pc", b"m3f1", no_drop=False, message_id=3)
    assert s.pop() == ("/pc", b"m3f1") and s.drops == {"/pc": 1}


def test_fragment_over_bound_breaks_the_whole_message() -> None:
    s = OutboundScheduler(10, 10)
    s.push("/pc", b"aaaaaa", no_drop=False, message_id=7)
    assert not s.push("/pc", b"bbbbbb", no_drop=False, message_id=7)
    assert not s.push("/pc", b"cc", no_drop=False, message_id=7)  # rest of a broken message
    assert drain(s) == [] and s.queued_bytes == 0


def test_wake_on_empty_to_nonempty_and_control_bound() -> None:
    calls: list[int] = []
    drops: list[tuple[str, int]] = []
    s = OutboundScheduler(10**6, 10, wake=lambda: calls.append(1),
                          on_drop=lambda t, n: drops.append((t, n)))
    s.push("/a", b"1", no_drop=False)
    s.push("/b", b"1", no_drop=False)
    assert calls == [1]
    drain(s)
    for _ in range(300):
        s.push_control("e")
    assert s.drops[CONTROL_TOPIC] == 300 - 256 and len(drops) == 44
    assert len(s.pop_batch(100)) == 100


def test_backlog_goes_first_outside_the_fifo_bounds() -> None:
    woken: list[int] = []
    s = OutboundScheduler(100, 2, wake=lambda: woken.append(1))
    s.push_backlog([("/e", b"m%d" % i) for i in range(5)])  # > 2 frames, > 100 bytes total
    assert woken == [1] and len(s) == 5 and s.backlog_frames == 5 and s.queued_bytes == 0
    assert s.push("/e", b"live1", no_drop=True)  # the FIFO bound counts live frames only
    assert s.push("/e", b"live2", no_drop=True)
    assert not s.push("/e", b"live3", no_drop=True)  # the live FIFO is full: counted
    assert s.push("/x", b"x", no_drop=False)  # backlog bytes leave room for droppable data
    assert [f for _, f in drain(s)] == [b"m0", b"m1", b"m2", b"m3", b"m4", b"live1",
                                        b"live2", b"x"]
    assert s.drops == {"/e": 1} and s.backlog_frames == 0 and s.backlog_bytes == 0
    assert s.queued_bytes == 0 and len(s) == 0


def test_ack_tracking_keeps_popped_no_drop_frames_until_acked() -> None:
    s = OutboundScheduler(10_000, 100)
    s.push("/e", b"e0", no_drop=True)
    assert s.pop() == ("/e", b"e0")
    assert s.ack_mark() is None and s.unacked_frames == 0  # not tracking: nothing kept
    s.track_acks()
    for i in range(1, 4):
        s.push("/e", b"e%d" % i, no_drop=True)
    s.push("/x", b"x", no_drop=False)
    assert [f for _, f in s.pop_batch(6)] == [b"e1", b"e2", b"e3"]  # 6 bytes: three frames
    first = s.ack_mark()
    assert first == 3 and s.ack_mark() is None  # nothing new since the mark
    s.push("/e", b"e4", no_drop=True)
    assert s.pop() == ("/e", b"e4")
    second = s.ack_mark()
    assert second == 4 and s.unacked_frames == 4
    s.acked(first)
    assert s.unacked_frames == 1  # e4 was sent after the first ping
    s.push("/e", b"e5", no_drop=True)
    # The connection is gone: unacknowledged, then queued, in order; droppable stays.
    assert s.take_no_drop() == [("/e", b"e4"), ("/e", b"e5")]
    assert s.unacked_frames == 0 and len(s) == 1 and s.queued_bytes == 1
    s.acked(second)  # a late pong changes nothing
    assert drain(s) == [("/x", b"x")]


def test_take_no_drop_includes_an_unsent_backlog() -> None:
    s = OutboundScheduler(10_000, 10)
    s.track_acks()
    s.push_backlog([("/e", b"b0"), ("/e", b"b1")])
    s.push("/e", b"l0", no_drop=True)
    assert s.pop() == ("/e", b"b0")
    assert [f for _, f in s.take_no_drop()] == [b"b0", b"b1", b"l0"]
    assert len(s) == 0 and s.queued_bytes == 0 and s.backlog_bytes == 0


def test_latched_messages_go_after_control_and_before_everything_else() -> None:
    woken: list[int] = []
    s = OutboundScheduler(10_000, 10, wake=lambda: woken.append(1))
    s.push_latched("/m", [b"m0", b"m1", b"m2"])  # the fragments of one message
    assert woken == [1] and len(s) == 3 and s.latched_frames == 3
    s.push("/x", b"x", no_drop=False)
    s.push("/e", b"e", no_drop=True)
    s.push_control("subscribed")
    s.push_latched("/t", [b"t"])
    assert drain(s) == [(CONTROL_TOPIC, "subscribed"), ("/m", b"m0"), ("/m", b"m1"),
                        ("/m", b"m2"), ("/t", b"t"), ("/e", b"e"), ("/x", b"x")]
    assert s.latched_bytes == 0 and s.queued_bytes == 0 and len(s) == 0


def test_latched_bound_drops_whole_messages_but_an_empty_queue_takes_one() -> None:
    s = OutboundScheduler(10, 10, max_latched_bytes=100)
    assert s.push_latched("/big", [b"a" * 80, b"b" * 80])  # alone: taken, over the bound
    assert not s.push_latched("/small", [b"c" * 10])  # dropped whole, counted
    assert s.push("/live", b"l", no_drop=False)  # the other queues' bound is separate
    assert [t for t, _ in drain(s)] == ["/big", "/big", "/live"]
    assert s.drops == {"/small": 1}
    assert s.push_latched("/small", [b"c" * 10, b"d" * 10]) and s.dropped_total == 1
