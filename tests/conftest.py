"""Settings every test shares."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

from tests.netns import Link, veth_link

# ROS 2 discovery stays on loopback for every rclpy node a test starts, in this process or
# in a child: the tests must not send multicast onto the machine's network, and on a
# loaded CI machine a test using multicast discovery missed its discovery deadline.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"


@pytest.fixture
def link() -> Iterator[Link]:
    """A veth pair into a fresh network namespace with a TCP/UDP sink (root only)."""
    yield from veth_link(os.getpid() % 200 + 20)
