"""The scheduler's keyframe rule and the per-topic feedback the video hook reads.

(Beside tests/client/test_scheduler.py, which another helper owns: same fakes.)
"""

from __future__ import annotations

import threading

from fleetctl.client.scheduler import Scheduler, SchedulerConfig

CAM = "/r1/camera"


def fake_split(frame: bytes, *, topic: str, message_id: int, max_fragment_bytes: int,
               no_drop: bool) -> list[bytes]:
    return [frame[i:i + max_fragment_bytes] for i in range(0, len(frame), max_fragment_bytes)]


def make() -> Scheduler:
    # Whole frames up to 100 bytes before any rate sample: "K..." of 300 bytes is split.
    return Scheduler(SchedulerConfig(max_fragment_bytes=100, initial_fragment_bytes=100),
                     split=fake_split)


def offer(sched: Scheduler, frame: bytes, keyframe: bool, now: float = 0.0,
          topic: str = CAM, priority: float = 1.0) -> None:
    sched.offer(topic, frame, now, priority=priority, no_drop=False, keyframe=keyframe)


def drain(sched: Scheduler) -> list[bytes]:
    out = []
    while (frame := sched.next_frame(1.0)) is not None:
        out.append(frame)
    return out


def test_a_delta_never_replaces_a_queued_keyframe() -> None:
    sched = make()
    offer(sched, b"K1", True)
    offer(sched, b"d2", False)  # depends on K1: dropped instead of K1
    assert drain(sched) == [b"K1"]
    stats = sched.stats()["topics"][CAM]  # type: ignore[index]
    assert stats["dropped_behind_keyframe"] == 1 and stats["dropped_replaced"] == 0
    assert sched.topic_feedback(CAM).dropped == 1


def test_a_keyframe_replaces_a_queued_delta_and_an_older_keyframe() -> None:
    sched = make()
    offer(sched, b"d1", False)
    offer(sched, b"K2", True)
    offer(sched, b"K3", True)
    assert drain(sched) == [b"K3"]
    assert sched.topic_feedback(CAM).dropped == 2


def test_deltas_still_replace_deltas() -> None:
    sched = make()
    offer(sched, b"d1", False)
    offer(sched, b"d2", False)
    assert drain(sched) == [b"d2"]


def test_a_keyframe_being_sent_is_not_superseded_by_a_delta() -> None:
    sched = make()
    offer(sched, b"K" * 300, True)
    first = sched.next_frame(1.0)  # one fragment of three out: the keyframe is in flight
    assert first == b"K" * 100
    offer(sched, b"d" * 10, False)  # waits behind the keyframe, which completes
    rest = [sched.next_frame(1.0) for _ in range(3)]
    assert rest == [b"K" * 100, b"K" * 100, b"d" * 10]
    assert sched.topic_feedback(CAM).dropped == 0


def test_a_keyframe_supersedes_a_delta_being_sent() -> None:
    sched = make()
    offer(sched, b"d" * 300, False)
    assert sched.next_frame(1.0) == b"d" * 100
    offer(sched, b"K" * 10, True)
    assert drain(sched) == [b"K" * 10]
    assert sched.stats()["topics"][CAM]["dropped_superseded"] == 1  # type: ignore[index]


def test_feedback_reports_busy_drops_bytes_and_higher_priority_use() -> None:
    sched = make()
    assert sched.topic_feedback(CAM).busy is False  # unknown topic: all zero
    offer(sched, b"K1", True)
    offer(sched, b"status", False, topic="/r1/status", priority=8.0)
    offer(sched, b"scan", False, topic="/r1/scan", priority=0.5)
    assert sched.topic_feedback(CAM).busy is True
    drain(sched)
    feedback = sched.topic_feedback(CAM)
    assert not feedback.busy and feedback.sent_bytes == 2 and feedback.dropped == 0
    assert feedback.higher_priority_sent_bytes == len(b"status")  # not the scan
    assert feedback.link_rate_Bps == 0.0  # no ack yet


def test_feedback_can_be_read_while_the_loop_thread_adds_topics() -> None:
    sched = make()
    stop = threading.Event()
    errors: list[BaseException] = []

    def reader() -> None:
        try:
            while not stop.is_set():
                sched.topic_feedback(CAM)
        except BaseException as exc:
            errors.append(exc)

    thread = threading.Thread(target=reader)
    thread.start()
    for i in range(20_000):
        offer(sched, b"x", False, topic=f"/t{i}")
    stop.set()
    thread.join()
    assert errors == []
