"""Fixtures of the rclpy tests: a context on the test module's own ROS domain."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest


@pytest.fixture
def ros(request: pytest.FixtureRequest) -> Iterator[tuple[object, object]]:
    """``(context, peer)``: an rclpy context on the module's ``DOMAIN_ID`` and a node spun
    by rclpy's executor, for the test's own publishers and subscribers."""
    rclpy = pytest.importorskip("rclpy")
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    context = Context()
    rclpy.init(context=context, domain_id=request.module.DOMAIN_ID)
    peer = Node("peer", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(peer)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        yield context, peer
    finally:
        executor.shutdown()
        thread.join(5)
        peer.destroy_node()
        context.try_shutdown()
