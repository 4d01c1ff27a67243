"""Run one rclpy node in the foreground until SIGTERM/SIGINT.

The small programs that are nothing but a node (the e2e load publisher, the native DDS
consumers) share this life cycle: their own context with rclpy's signal handlers off (so a
signal only sets a flag and the node finishes its current callback), spin in short steps,
then tear down in order.
"""

from __future__ import annotations

import signal
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

SPIN_STEP_S = 0.05  # how quickly a stop signal is noticed


def spin_until_signal(node_name: str, setup: Callable[[Any], None]) -> None:
    """Create node *node_name*, let *setup* add its entities, spin until SIGTERM/SIGINT.

    Args:
        node_name: ROS node name.
        setup: Called once with the node before spinning (create publishers,
            subscriptions, timers there).
    """
    stop = False

    def on_signal(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(node_name, context=context)
    executor = SingleThreadedExecutor(context=context)
    try:
        setup(node)
        executor.add_node(node)
        while not stop:
            executor.spin_once(timeout_sec=SPIN_STEP_S)
    finally:
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()
