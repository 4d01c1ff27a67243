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


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Two xdist groups for ``pytest -n 2 --dist loadgroup`` (scripts/test.sh): a module
    marked ``own_worker`` (the e2e scenario run: ~9.5 min spent mostly waiting on timed
    phases) is one group, every other test the other, in its usual order.

    Why not plain ``-n 2``: the other tests were written to run one at a time (docker
    fleets, network namespaces, a browser, timed phases on two cores); two of them at once
    is not what they were checked against. The e2e run shares nothing with them but the
    CPU: its containers, networks and volumes carry its own run id, it publishes no host
    port, and its image build is a no-op after the script's ``fleetctl build``. Without
    ``-n`` the groups are ignored and everything runs serially, as before.
    """
    for item in items:
        own = item.get_closest_marker("own_worker") is not None
        group = item.module.__name__ if own and item.module is not None else "suite"
        item.add_marker(pytest.mark.xdist_group(group))


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
