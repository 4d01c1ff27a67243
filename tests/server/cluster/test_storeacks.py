"""StoreAcks: which no_drop frames the sessions' stream has stored, and who waits."""

from __future__ import annotations

from fleetctl.server.cluster.storeacks import StoreAcks


def test_a_mark_is_stored_once_every_frame_up_to_it_is_done() -> None:
    acks = StoreAcks()
    first, second = acks.note_offered(), acks.note_offered()
    assert (first, second) == (1, 2)
    assert acks.stored(0) and not acks.stored(1)
    acks.note_done()
    assert acks.stored(1) and not acks.stored(2)


def test_waiters_are_called_in_mark_order_when_their_frames_are_done() -> None:
    acks = StoreAcks()
    for _ in range(3):
        acks.note_offered()
    called: list[str] = []
    acks.wait(3, lambda: called.append("c3"))
    acks.wait(1, lambda: called.append("a1"))
    acks.wait(1, lambda: called.append("b1"))
    acks.wait(0, lambda: called.append("now"))  # nothing to wait for: at once
    assert called == ["now"]
    acks.note_done()
    assert called == ["now", "a1", "b1"]
    acks.note_done()
    assert called == ["now", "a1", "b1"]
    acks.note_done()
    assert called == ["now", "a1", "b1", "c3"]


def test_nothing_waits_while_the_stream_is_away() -> None:
    acks = StoreAcks()
    acks.note_offered()
    called: list[int] = []
    acks.wait(1, lambda: called.append(1))
    acks.set_bypass(True)
    assert called == [1] and acks.stored(5)
    acks.set_bypass(False)
    assert not acks.stored(1)


def test_a_failing_callback_does_not_hold_the_others() -> None:
    acks = StoreAcks()
    acks.note_offered()
    called: list[int] = []

    def broken() -> None:
        raise RuntimeError("a connection's bug")

    acks.wait(1, broken)
    acks.wait(1, lambda: called.append(1))
    acks.note_done()
    assert called == [1]


def test_release_all_calls_everyone() -> None:
    acks = StoreAcks()
    acks.note_offered()
    called: list[int] = []
    acks.wait(1, lambda: called.append(1))
    acks.release_all()
    assert called == [1]
