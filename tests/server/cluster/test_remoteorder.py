"""ReceiverOrder and SenderOrder: another replica's no_drop frames in their sender's order."""

from __future__ import annotations

import pytest

from fleetctl.server.cluster import remoteorder
from fleetctl.server.cluster.remoteorder import (
    MAX_HELD_FRAMES,
    ReceiverOrder,
    SenderOrder,
    covered_by,
    order_subject,
)
from tests.support import wait_until


def receiver() -> tuple[ReceiverOrder, list[bytes], dict[str, int]]:
    got: list[bytes] = []
    counters: dict[str, int] = {}
    return ReceiverOrder(got.append, counters), got, counters


def frames(sender: SenderOrder, subject: str, n: int) -> list[tuple[str, bytes]]:
    return [(sender.stamp(subject), f"{subject}-{i}".encode()) for i in range(n)]


def test_the_sender_numbers_frames_and_links_each_to_its_subjects_previous() -> None:
    sender = SenderOrder("e1")
    assert sender.stamp("a") == "e1:1:0"
    assert sender.stamp("b") == "e1:2:0"
    assert sender.stamp("a") == "e1:3:1"
    assert sender.stamp("b") == "e1:4:2"
    assert SenderOrder().epoch != SenderOrder().epoch


async def test_frames_in_order_go_at_once() -> None:
    order, got, counters = receiver()
    sent = frames(SenderOrder(), "husky1.events", 5)
    for stamp, frame in sent:
        order.offer(stamp, "husky1.events", frame)
    assert got == [f for _, f in sent] and counters["order_held"] == 0


async def test_a_frame_after_a_gap_waits_for_the_missing_one() -> None:
    order, got, counters = receiver()
    sent = frames(SenderOrder(), "s", 5)
    for i in (0, 1, 3, 4):  # frame 2's core copy was lost
        order.offer(sent[i][0], "s", sent[i][1])
    assert got == [sent[0][1], sent[1][1]] and order.held == 2
    order.offer(sent[2][0], "s", sent[2][1])  # it comes from the stream
    assert got == [f for _, f in sent] and order.held == 0
    assert counters["order_held"] == 2 and counters["order_skipped"] == 0


async def test_subjects_and_senders_are_ordered_apart() -> None:
    order, got, _ = receiver()
    a, b = SenderOrder("a"), SenderOrder("b")
    a1, a2, b1 = a.stamp("x"), a.stamp("x"), b.stamp("x")
    other = a.stamp("y")
    order.offer(a1, "x", b"a1")
    order.offer(other, "y", b"y1")  # another subject of the same sender: its own chain
    order.offer(b1, "x", b"b1")  # another sender on the same subject
    order.offer(a2, "x", b"a2")
    assert got == [b"a1", b"y1", b"b1", b"a2"]


async def test_a_gap_is_skipped_after_the_hold_and_a_late_frame_still_delivered(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(remoteorder, "HOLD_S", 0.05)
    order, got, counters = receiver()
    sent = frames(SenderOrder(), "s", 4)
    order.offer(sent[0][0], "s", sent[0][1])
    order.offer(sent[2][0], "s", sent[2][1])
    order.offer(sent[3][0], "s", sent[3][1])
    await wait_until(lambda: len(got) == 3, 5.0)
    assert got == [sent[0][1], sent[2][1], sent[3][1]]
    assert counters["order_skipped"] == 1 and order.held == 0
    order.offer(sent[1][0], "s", sent[1][1])  # late: delivered, not lost
    assert got[-1] == sent[1][1] and counters["order_late"] == 1


async def test_frames_without_an_order_or_with_a_bad_one_go_at_once() -> None:
    order, got, counters = receiver()
    order.offer(None, "s", b"latest-only")
    order.offer("not:an:order:value", "s", b"odd")
    order.offer("e:x:1", "s", b"odder")
    assert got == [b"latest-only", b"odd", b"odder"] and counters["order_malformed"] == 2


async def test_a_subject_no_longer_followed_is_forgotten_with_its_held_frames() -> None:
    order, got, _ = receiver()
    sender = SenderOrder()
    sent = frames(sender, "husky1.events", 3)
    order.offer(sent[0][0], "husky1.events", sent[0][1])
    order.offer(sent[2][0], "husky1.events", sent[2][1])  # held
    order.forget(covered_by(["fleetctl.husky2.>"]))
    assert got == [sent[0][1], sent[2][1]] and order.held == 0
    later = sender.stamp("husky1.events")  # followed again: a fresh start
    order.offer(later, "husky1.events", b"again")
    assert got[-1] != b"again"  # its predecessors could still come from the stream...
    order.offer_stream(later, "husky1.events", b"again", first=False)
    assert got[-1] == b"again"  # ... until the stream brings its own copy: none will


async def test_the_first_frame_over_core_waits_for_what_the_stream_still_brings() -> None:
    """The sender learnt of this replica's interest late: frames 0-2 reach it only
    through the stream, which lags; frame 3's core copy comes first."""
    order, got, counters = receiver()
    sent = frames(SenderOrder(), "s", 5)
    order.offer(sent[3][0], "s", sent[3][1])
    order.offer(sent[4][0], "s", sent[4][1])
    assert got == [] and order.held == 2
    for i in range(3):
        order.offer_stream(sent[i][0], "s", sent[i][1], first=True)
    assert got == [f for _, f in sent] and order.held == 0
    order.offer_stream(sent[3][0], "s", sent[3][1], first=False)  # seconds: nothing more
    order.offer_stream(sent[4][0], "s", sent[4][1], first=False)
    assert len(got) == 5 and counters["order_late"] == 0


async def test_the_stream_vouches_for_a_held_frame_whose_predecessor_never_comes() -> None:
    order, got, _ = receiver()
    sent = frames(SenderOrder(), "s", 4)
    order.offer(sent[0][0], "s", sent[0][1])
    order.offer(sent[2][0], "s", sent[2][1])  # frame 1 was never stored nor sent here
    order.offer(sent[3][0], "s", sent[3][1])
    assert got == [sent[0][1]]
    order.offer_stream(sent[2][0], "s", sent[2][1], first=False)
    assert got == [sent[0][1], sent[2][1], sent[3][1]] and order.held == 0


async def test_held_frames_are_bounded() -> None:
    order, got, counters = receiver()
    sender = SenderOrder()
    first = sender.stamp("s")
    order.offer(first, "s", b"first")
    sender.stamp("s")  # lost for good
    for i in range(MAX_HELD_FRAMES + 5):
        order.offer(sender.stamp("s"), "s", b"%d" % i)
    assert order.held <= MAX_HELD_FRAMES
    assert counters["order_skipped"] >= 1 and len(got) == MAX_HELD_FRAMES + 6 - order.held
    order.close()
    assert order.held == 0 and len(got) == MAX_HELD_FRAMES + 6


def test_both_copies_share_their_subject_after_the_root() -> None:
    assert order_subject("fleetctl.husky1.events") == "husky1.events"
    assert order_subject("fleetctl_nd.husky1.events") == "husky1.events"
    keep = covered_by(["fleetctl.husky1.>", "fleetctl.jackal2.pose", "fleetctl.r9.*.x"])
    assert keep("husky1.events") and keep("husky1.a.b") and keep("jackal2.pose")
    assert not keep("jackal2.scan") and not keep("husky1") and not keep("husky2.events")
    assert keep("r9.cam.x") and not keep("r9.cam.y")
    assert covered_by(["fleetctl.>"])("anything.at.all")
