"""A one-node executor with one wait per message, for the robot client.

rclpy's ``SingleThreadedExecutor`` (Jazzy) rebuilds its wait set in Python from every node's
entity lists on each wait, wraps each callback in a :class:`rclpy.task.Task`, and triggers
its own guard condition twice per callback, so every message costs two full wait rounds.
For a 10 Hz 1 MB point cloud that overhead is about a third of a percent of a core, as
much as taking the message from DDS (measured with ``benchmarks/client_process.py`` and a
bare subscriber spun both ways: 1.4 % with rclpy's executor, 1.0-1.2 % with this loop).

:class:`NodeExecutor` spins exactly one node in the calling thread: its subscriptions,
timers, guard conditions and waitables (the QoS event handlers rclpy attaches to
subscriptions), in one wait set per round, and calls callbacks directly. It does not serve
services or clients, and runs no coroutines: the client node is created without parameter
services (its settings come from the YAML file) and has no services or clients of its own.
Subscriptions whose callback is a :class:`~fleetctl.client.ros.intake.LoopServed` are left
to the asyncio loop's thread (:mod:`fleetctl.client.ros.intake`); one whose callback is a
:class:`~fleetctl.client.ros.intake.TakesInfo` gets the take's source timestamp and
publication sequence number too, as the loop's intake passes them.

It uses the wait set of rclpy's C extension (``rclpy_implementation.WaitSet``), as rclpy's
executors do; that API is internal to rclpy, so ``tests/client/ros/test_executor.py`` runs it
against the installed rclpy.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Coroutine
from contextlib import ExitStack
from typing import Any

from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.context import Context
from rclpy.exceptions import InvalidHandle
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node

from fleetctl.client.ros.intake import LoopServed, TakesInfo, message_info

log = logging.getLogger(__name__)

WAIT_TIMEOUT_NS = 1_000_000_000  # a bound on each wait; shutdown wakes it earlier anyway


class NodeExecutor:
    """Spins one node (see the module docstring).

    Args:
        node: The node; its entity lists are read again on every round, so subscriptions
            created or destroyed by its own callbacks are picked up.
        context: The node's rclpy context.
    """

    def __init__(self, node: Node, context: Context) -> None:
        self._node = node
        self._context = context
        self._stopping = threading.Event()
        self._wake = GuardCondition(None, None, context=context)
        self.rounds = 0  # waits done: a test's view of spurious wakeups
        context.on_shutdown(self.shutdown)

    def spin(self) -> None:
        """Run rounds until :meth:`shutdown` or the context shuts down."""
        while not self._stopping.is_set() and self._context.ok():
            self.spin_once(WAIT_TIMEOUT_NS)

    def shutdown(self) -> None:
        """Stop :meth:`spin` (from any thread): the current wait returns at once."""
        self._stopping.set()
        with contextlib.suppress(InvalidHandle):  # a gone context: nothing is waiting
            self._wake.trigger()

    def spin_once(self, timeout_ns: int) -> None:
        """Wait up to *timeout_ns* for work, then run every ready callback once."""
        self.rounds += 1
        node = self._node
        with ExitStack() as held:
            # Entering a handle keeps it alive (not destroyed) while the wait set uses it.
            subscriptions = _enter_all(held, [
                sub for sub in node.subscriptions if not isinstance(sub.callback, LoopServed)])
            timers = _enter_all(held, list(node.timers))
            guards = _enter_all(held, [*node.guards, self._wake])
            waitables = _enter_all(held, list(node.waitables), handle=False)
            context_handle = self._context.handle
            if context_handle is None:  # shut down: nothing to wait for
                return
            held.enter_context(context_handle)
            wait_set = _wait_set(context_handle, subscriptions, timers, guards, waitables)
            wait_set.wait(timeout_ns)
            if self._stopping.is_set() or not self._context.ok():
                return
            ready_timers = wait_set.get_ready_entities("timer")
            ready_subscriptions = wait_set.get_ready_entities("subscription")
            ready_guards = wait_set.get_ready_entities("guard_condition")
            ready_waitables = [w for w in waitables if w.is_ready(wait_set)]
        for timer in timers:
            if timer.handle.pointer in ready_timers:
                self._run_timer(timer)
        for sub in subscriptions:
            if sub.handle.pointer in ready_subscriptions:
                self._run_subscription(sub)
        for guard in guards:
            if guard is not self._wake and guard.handle.pointer in ready_guards \
                    and guard.callback is not None:
                _call(guard.callback)
        for waitable in ready_waitables:
            self._run_waitable(waitable)

    @staticmethod
    def _run_timer(timer: Any) -> None:
        try:
            with timer.handle:
                if not timer.handle.is_timer_ready():  # cancelled since the wait
                    return
                timer.handle.call_timer()
        except InvalidHandle:  # destroyed by an earlier callback of this round
            return
        _call(timer.callback)

    @staticmethod
    def _run_subscription(sub: Any) -> None:
        try:
            with sub.handle:
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
        except InvalidHandle:
            return
        if taken is None:  # rmw said ready, but the sample was gone (e.g. lost to depth)
            return
        if isinstance(sub.callback, TakesInfo):
            _call(sub.callback.callback, taken[0], *message_info(taken[1]))
        else:
            _call(sub.callback, taken[0])

    @staticmethod
    def _run_waitable(waitable: Any) -> None:
        try:
            data = waitable.take_data()
        except InvalidHandle:
            return
        _drive(waitable.execute(data))


def steady_timer(node: Node, period_s: float, callback: Callable[[], Any]) -> Any:
    """A timer of *node* on the steady clock, for the client's own periodic work (status,
    QoS refresh, TF ticks), which is about elapsed time, not ROS time.

    rclpy's default (ROS time, i.e. the wall clock without sim time) stops a timer when the
    wall clock steps back: its next call stays at the old time. A robot whose clock chrony
    stepped back an hour at boot sent no status, re-read no publisher QoS and re-sent no
    latched map for that hour (reproduced with libfaketime: a 0.2 s timer ticked once in
    3 s after a 1 h step back, a steady one 15 times).
    """
    return node.create_timer(period_s, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


def _enter_all(held: ExitStack, entities: list[Any], *, handle: bool = True) -> list[Any]:
    """The entities that could be entered (destroyed ones are skipped): their handles,
    or with ``handle=False`` the entities themselves (waitables are context managers)."""
    alive = []
    for entity in entities:
        try:
            held.enter_context(entity.handle if handle else entity)
        except InvalidHandle:
            continue
        alive.append(entity)
    return alive


def _wait_set(context_handle: Any, subscriptions: list[Any], timers: list[Any],
              guards: list[Any], waitables: list[Any]) -> Any:
    """An rcl wait set holding all of these (each waitable adds its own entities:
    rclpy's QoS event handlers add events)."""
    extra = [0] * 6
    for waitable in waitables:
        n = waitable.get_num_entities()
        for i, count in enumerate((n.num_subscriptions, n.num_guard_conditions, n.num_timers,
                                   n.num_clients, n.num_services, n.num_events)):
            extra[i] += count
    wait_set = _rclpy.WaitSet(
        len(subscriptions) + extra[0], len(guards) + extra[1], len(timers) + extra[2],
        extra[3], extra[4], extra[5], context_handle)
    wait_set.clear_entities()
    for sub in subscriptions:
        wait_set.add_subscription(sub.handle)
    for timer in timers:
        wait_set.add_timer(timer.handle)
    for guard in guards:
        wait_set.add_guard_condition(guard.handle)
    for waitable in waitables:
        waitable.add_to_wait_set(wait_set)
    return wait_set


def _call(callback: Any, *args: Any) -> None:
    """Run one callback; a failing callback is logged and never stops the loop."""
    try:
        result = callback(*args)
        if isinstance(result, Coroutine):
            _drive(result)
    except Exception:
        log.exception("callback %r failed", callback)


def _drive(coroutine: Coroutine[Any, Any, Any]) -> None:
    """Run a coroutine that never really suspends (rclpy's event handlers) to its end."""
    try:
        coroutine.send(None)
    except StopIteration:
        return
    except Exception:
        log.exception("waitable callback failed")
        return
    coroutine.close()
    log.warning("a waitable's callback awaited something; this executor does not run it")
