"""Take local messages in the asyncio loop's thread, woken by the middleware itself.

With an rclpy executor in its own thread, every message of a ``publish`` topic wakes two
threads: DDS wakes the executor (a wait-set round), and the executor, having encoded the
frame, wakes the asyncio loop to send it (``call_soon_threadsafe``'s self-pipe). Each
cross-CPU wake costs about 0.06 ms of CPU on a VM and the wait set's round as much again:
for a 10 Hz 1 MB point cloud, a quarter of the client's cost above a bare subscriber.

:class:`LoopIntake` removes the executor from that path. rmw's "new message" callback
(``rcl_subscription_set_on_new_message_callback``, which rclcpp's events executor uses; rclpy
does not expose it) is pointed straight at libc's ``eventfd_write`` with the subscription's
eventfd as its user data: the middleware's thread bumps the eventfd and nothing else (no
Python, so no GIL: a Python callback there could deadlock against a thread that holds the
GIL while it waits in ``take`` for the reader's lock that the middleware holds during the
callback). The loop watches the eventfds like any socket, and when one is readable takes
every waiting message of that subscription (raw CDR) and runs its callback right there, so
the frame is queued on the link without another hop.

The callback has the signature ``void(const void *user_data, size_t number_of_events)`` and
``eventfd_write`` is ``int(int fd, uint64_t value)``: on x86-64 and AArch64 Linux both
arguments travel in the same registers (the fd in the low half of the first), and the return
value is ignored, so the call adds *number_of_events* to the eventfd. Elsewhere, or without
the rcl symbol, :func:`load_wakeups` returns None and the client keeps its executor path.

Subscriptions served this way carry a :class:`LoopServed` callback, which the client's
executor (:mod:`fleetctl.client.ros.executor`) skips: it is set when the subscription is
created, so no executor round ever takes one of their messages.

With a *sender* (the robot link), the frames offered during one take are written at its
end, in this same turn of the loop, rather than by the link's send loop in the next round
(:meth:`fleetctl.client.transport.RobotLink.send_held`).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import logging
import os
import platform
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from rclpy.exceptions import InvalidHandle

log = logging.getLogger(__name__)

# Messages taken per wake and subscription before the loop gets a turn (the rest are taken
# on the next round: the eventfd stays readable).
MAX_TAKES_PER_ROUND = 64
_ABI_OK = sys.platform == "linux" and platform.machine() in ("x86_64", "aarch64")
_RCL_LIBRARY = "librcl.so"  # loaded by rclpy already; dlopen finds it by this name


class HeldSender(Protocol):
    """What :class:`LoopIntake` needs of the link: hold its send loop's wakes during a
    take, then write what was offered."""

    def hold_wakes(self) -> None: ...

    def send_held(self) -> None: ...


class MessageCallback(Protocol):
    """What a loop-served subscription's messages go to: the raw CDR, the middleware's
    source timestamp (when the publisher published it, wall clock ns; 0 when not known)
    and the sample's publication sequence number (its writer's 1, 2, 3, ...; 0 when not
    known), which rclpy's executor does not pass on (the client's does,
    :class:`TakesInfo`). The robot link judges a message after an outage by the first
    (fleetctl.client.transport.RobotLink.offer); gaps in the second are messages DDS
    lost (fleetctl.client.seqgaps)."""

    def __call__(self, cdr: bytes, published_ns: int = 0, sequence: int = 0, /) -> None: ...


class TakesInfo:
    """A subscription callback that wants the take's message info: the client's executor
    (:mod:`fleetctl.client.ros.executor`) calls the wrapped callback with the CDR, the
    publish time and the sequence number (:func:`message_info`).

    Calling it calls the wrapped callback with the CDR only, so nothing breaks if
    something else (rclpy's executor) does.
    """

    __slots__ = ("callback",)

    def __init__(self, callback: MessageCallback) -> None:
        self.callback = callback

    def __call__(self, cdr: bytes) -> None:
        self.callback(cdr)


class LoopServed(TakesInfo):
    """A :class:`TakesInfo` that marks its subscription as served by a :class:`LoopIntake`
    (the client's executor leaves it alone)."""

    __slots__ = ()


@dataclass(frozen=True)
class Wakeups:
    """The C entry points :class:`LoopIntake` needs.

    Attributes:
        set_callback: ``rcl_subscription_set_on_new_message_callback``.
        eventfd_write: Address of libc's ``eventfd_write``.
    """

    set_callback: Any
    eventfd_write: int

    def point_at(self, subscription_pointer: int, fd: int | None) -> None:
        """Make the subscription's new messages bump *fd* (None: stop).

        Raises:
            OSError: rcl refused (its return code is in the message).
        """
        if fd is None:
            ret = self.set_callback(subscription_pointer, None, None)
        else:
            ret = self.set_callback(subscription_pointer, self.eventfd_write, fd)
        if ret != 0:
            raise OSError(f"rcl_subscription_set_on_new_message_callback returned {ret}")


def load_wakeups() -> Wakeups | None:
    """The C entry points, or None where this mechanism is not available (then the
    executor serves every subscription)."""
    if not _ABI_OK:
        return None
    try:
        rcl = ctypes.CDLL(_RCL_LIBRARY)
        set_callback = rcl.rcl_subscription_set_on_new_message_callback
        libc = ctypes.CDLL(None)
        eventfd_write = ctypes.cast(libc.eventfd_write, ctypes.c_void_p).value
    except (OSError, AttributeError) as exc:
        log.info("new-message callbacks unavailable (%s): the executor takes all messages", exc)
        return None
    if eventfd_write is None:
        return None
    set_callback.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
    set_callback.restype = ctypes.c_int
    return Wakeups(set_callback, eventfd_write)


class _Served:
    """One subscription's eventfd and callback."""

    __slots__ = ("callback", "fd", "subscription")

    def __init__(self, subscription: Any, callback: MessageCallback, fd: int) -> None:
        self.subscription = subscription
        self.callback = callback
        self.fd = fd


class LoopIntake:
    """Serves raw subscriptions in the thread of *loop* (see the module docstring).

    Args:
        loop: The running asyncio loop whose thread takes the messages.
        wakeups: From :func:`load_wakeups`.
        sender: The link the callbacks offer frames to (see the module docstring);
            None: they wake the link as usual.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, wakeups: Wakeups,
                 sender: HeldSender | None = None) -> None:
        self._loop = loop
        self._wakeups = wakeups
        self._sender = sender
        self._served: dict[int, _Served] = {}  # by id(subscription)
        self._lock = threading.Lock()
        self._closed = False
        self.taken = 0
        self.failed_callbacks = 0

    def attach(self, subscription: Any) -> None:
        """Serve *subscription* (created with a :class:`LoopServed` callback); any thread.

        Raises:
            OSError: No eventfd, or rcl refused the callback (the caller falls back).
            ValueError: The subscription's callback is not a :class:`LoopServed`.
        """
        served_callback = subscription.callback
        if not isinstance(served_callback, LoopServed):
            raise ValueError("attach() needs a subscription created with a LoopServed callback")
        fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        served = _Served(subscription, served_callback.callback, fd)
        try:
            with subscription.handle:
                self._wakeups.point_at(subscription.handle.pointer, fd)
        except BaseException:
            os.close(fd)
            raise
        with self._lock:
            if self._closed:
                self._unpoint(served)
                os.close(fd)
                return
            self._served[id(subscription)] = served
        # Messages that arrived before this are counted in the eventfd already (rmw calls
        # back at once with the unread count), so the first round takes them.
        self._on_loop(self._loop.add_reader, fd, self._drain, served)

    def detach(self, subscription: Any) -> None:
        """Stop serving *subscription* before it is destroyed; any thread."""
        with self._lock:
            served = self._served.pop(id(subscription), None)
        if served is not None:
            self._release(served)

    def close(self) -> None:
        """Detach everything (before the node is destroyed); any thread."""
        with self._lock:
            self._closed = True
            served, self._served = list(self._served.values()), {}
        for item in served:
            self._release(item)

    def _release(self, served: _Served) -> None:
        # Once rcl has dropped the callback the middleware never writes the fd again, so it
        # may be closed (on the loop, after its reader is removed: no round uses it then).
        self._unpoint(served)
        self._on_loop(self._forget, served)

    def _unpoint(self, served: _Served) -> None:
        try:
            with served.subscription.handle:
                self._wakeups.point_at(served.subscription.handle.pointer, None)
        except InvalidHandle:
            pass  # destroyed already: its listener, and the callback with it, is gone
        except OSError as exc:
            log.warning("could not clear the new-message callback of %s: %s",
                        served.subscription.topic_name, exc)

    def _forget(self, served: _Served) -> None:
        self._loop.remove_reader(served.fd)
        os.close(served.fd)

    def _on_loop(self, fn: Callable[..., Any], *args: Any) -> None:
        if self._loop.is_closed():
            return
        if _in_loop_thread(self._loop):
            fn(*args)
        else:
            with contextlib.suppress(RuntimeError):  # the loop closed in between
                self._loop.call_soon_threadsafe(fn, *args)

    def _drain(self, served: _Served) -> None:
        """Take what waits (up to :data:`MAX_TAKES_PER_ROUND`) and run the callback."""
        # Reset the count first: a message arriving after the last take makes it readable
        # again, so no wake is lost.
        with contextlib.suppress(BlockingIOError):
            os.eventfd_read(served.fd)
        sender = self._sender
        if sender is None:
            self._take(served)
            return
        sender.hold_wakes()
        try:
            self._take(served)
        finally:
            sender.send_held()

    def _take(self, served: _Served) -> None:
        sub = served.subscription
        for _ in range(MAX_TAKES_PER_ROUND):
            try:
                with sub.handle:
                    taken = sub.handle.take_message(sub.msg_type, True)
            except InvalidHandle:
                return  # destroyed under us (a QoS switch): its successor is attached
            if taken is None:
                return
            self.taken += 1
            try:
                served.callback(taken[0], *message_info(taken[1]))
            except Exception:  # one bad message must not stop the intake
                self.failed_callbacks += 1
                log.exception("callback of %s failed", sub.topic_name)
        os.eventfd_write(served.fd, 1)  # more may wait: come back after others had a turn


def message_info(info: Any) -> tuple[int, int]:
    """``(source timestamp ns, publication sequence number)`` of a take's message info (a
    dict in rclpy); 0 for what it lacks."""
    if not isinstance(info, dict):
        return 0, 0
    return _positive(info.get("source_timestamp")), _positive(
        info.get("publication_sequence_number"))


def _positive(value: Any) -> int:
    return value if isinstance(value, int) and value > 0 else 0


def _in_loop_thread(loop: asyncio.AbstractEventLoop) -> bool:
    try:
        return asyncio.get_running_loop() is loop
    except RuntimeError:
        return False
