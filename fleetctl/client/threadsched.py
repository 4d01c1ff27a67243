"""Keep a library from raising this process's threads to real-time scheduling.

Why: SVT-AV1 (v4.1, PyAV's ``libsvtav1``) switches the thread that opens an encoder, and
the threads it starts, to ``SCHED_FIFO`` priority 99 whenever it is allowed to (as root, or
with an ``RLIMIT_RTPRIO``). A busy thread at the top real-time priority starves everything
else on its core: on a robot, the control loops; and every process forked afterwards
inherits the policy. In CI it left the test process at FIFO 99, so a ``docker`` CLI spun
at 95 % of a core for half an hour and Chromium starved a browser test. A camera encoder
must run at normal priority, so :func:`no_realtime_promotion` puts back what changed.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator

log = logging.getLogger("fleetctl.client.video")

REALTIME_POLICIES = frozenset({os.SCHED_FIFO, os.SCHED_RR})


def _policies() -> dict[int, int]:
    """Scheduling policy of every thread of this process, by thread id."""
    found = {}
    for entry in os.listdir("/proc/self/task"):
        try:
            found[int(entry)] = os.sched_getscheduler(int(entry))
        except OSError:  # the thread ended since the listing
            continue
    return found


def realtime_threads() -> list[int]:
    """Ids of this process's threads that run a real-time policy (FIFO or RR)."""
    return [tid for tid, policy in _policies().items() if policy in REALTIME_POLICIES]


def demote(tids: list[int]) -> int:
    """Put threads *tids* back to ``SCHED_OTHER``; returns how many were changed."""
    changed = 0
    for tid in tids:
        try:
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            changed += 1
        except OSError:  # ended meanwhile
            continue
    return changed


@contextlib.contextmanager
def no_realtime_promotion(what: str) -> Iterator[None]:
    """Undo, when the block ends, any real-time policy a thread got inside it.

    Threads already real-time before the block (an operator's ``chrt``) are left alone.

    Args:
        what: Names the code in the log line (e.g. ``"libsvtav1"``).
    """
    before = _policies()
    try:
        yield
    finally:
        raised = [tid for tid, policy in _policies().items()
                  if policy in REALTIME_POLICIES and before.get(tid) not in REALTIME_POLICIES]
        if raised and demote(raised):
            log.info("%s raised %d thread(s) to real-time scheduling; put back to normal",
                     what, len(raised))
