"""Settings every test shares."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

from fleetctl.client.threadsched import demote, realtime_threads
from tests.netns import Link, veth_link

# ROS 2 discovery stays on loopback for every rclpy node a test starts, in this process or
# in a child: the tests must not send multicast onto the machine's network, and on a
# loaded CI machine a test using multicast discovery missed its discovery deadline.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"


@pytest.fixture
def link() -> Iterator[Link]:
    """A veth pair into a fresh network namespace with a TCP/UDP sink (root only)."""
    yield from veth_link(os.getpid() % 200 + 20)


@pytest.fixture(autouse=True)
def _no_thread_left_real_time() -> Iterator[None]:
    """Fail a test that leaves a thread of the test process at a real-time policy.

    Why: every process the suite forks afterwards inherits it. An SVT-AV1 encoder once left
    the main thread at SCHED_FIFO 99 (fleetctl/client/threadsched.py), and two cores later
    spun a docker CLI and Chromium at that priority: the run starved and hung. The threads
    are put back, so the tests after it run as usual.
    """
    yield
    raised = realtime_threads()
    if raised:
        demote(raised)
        pytest.fail(f"{len(raised)} thread(s) of the test process left at a real-time "
                    "scheduling policy (put back to SCHED_OTHER)")
