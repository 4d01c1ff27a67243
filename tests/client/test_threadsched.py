"""no_realtime_promotion: a thread raised to real-time inside the block is put back."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator

import pytest

from fleetctl.client.threadsched import no_realtime_promotion


def _try_fifo(tid: int) -> None:
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(1))
    except PermissionError:
        pytest.skip("needs root or an RLIMIT_RTPRIO to set a real-time policy")


@pytest.fixture
def worker() -> Iterator[tuple[int, threading.Event]]:
    """A live thread (its native id) that ends when the event is set."""
    done = threading.Event()
    thread = threading.Thread(target=done.wait, args=(30,), daemon=True)
    thread.start()
    assert thread.native_id is not None
    yield thread.native_id, done
    done.set()
    thread.join(timeout=30)


def test_a_thread_raised_inside_the_block_is_put_back(
        worker: tuple[int, threading.Event], caplog: pytest.LogCaptureFixture) -> None:
    tid, _ = worker
    caplog.set_level("INFO", logger="fleetctl.client.video")
    with no_realtime_promotion("a test library"):
        _try_fifo(tid)
        assert os.sched_getscheduler(tid) == os.SCHED_FIFO
    assert os.sched_getscheduler(tid) == os.SCHED_OTHER
    assert "a test library raised 1 thread(s) to real-time scheduling" in caplog.text


def test_a_thread_real_time_before_the_block_stays(
        worker: tuple[int, threading.Event]) -> None:
    tid, _ = worker
    _try_fifo(tid)  # as an operator's chrt would
    try:
        with no_realtime_promotion("a test library"):
            pass
        assert os.sched_getscheduler(tid) == os.SCHED_FIFO
    finally:
        os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
