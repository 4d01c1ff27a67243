"""Helpers shared by the test packages: frames to send, deadline-bounded waits, a
clock moved by hand, an event loop on virtual time, a process paused for certain and a ROS
domain no other test run on this host uses."""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import os
import signal
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from fleetctl.wire.codec import default_codec
from fleetctl.wire.compression import COMPRESSED_TYPE

STRING_TYPE = "std_msgs/msg/String"
# ROS domains no test module has as its own, and outside the benchmarks' (soak_client:
# 60-89, client_process and peer_latency: 100-199, robot_graph: 86): a module whose domain
# another process holds takes one of these (ros_domain_alone).
SPARE_ROS_DOMAINS = range(91, 100)
_HELD_DOMAINS: list[IO[str]] = []  # open lock files: held until this process exits


class ManualClock:
    """A monotonic clock (seconds) that a test moves by hand, for the components that
    take a ``clock`` callable."""

    def __init__(self, start_s: float = 100.0) -> None:
        self.now_s = start_s

    def __call__(self) -> float:
        return self.now_s


@contextlib.contextmanager
def virtual_time(loop: asyncio.AbstractEventLoop) -> Iterator[None]:
    """Run *loop* on virtual time while the block runs: ``loop.time()`` stands still
    while callbacks run and jumps to the next timer when nothing else is ready.

    For code paced by the loop's own timers (``call_later``, ``asyncio.sleep``,
    ``asyncio.timeout``): on a loaded test host a real loop wakes milliseconds late, which
    makes assertions on when things happened flaky; here they happen exactly when
    scheduled, and a 0.6 s schedule runs in no real time. Real I/O still works (ready
    events are polled without blocking); a loop with nothing ready and no timer blocks on
    its selector as usual. Work in other threads (``run_in_executor``, hence
    ``loop.getaddrinfo``) is not waited for: time runs past it, so a test replaces it.

    Uses the loop's ``_selector``, private to asyncio's selector event loops.
    """
    selector = loop._selector  # type: ignore[attr-defined]
    real_select = selector.select
    now = [loop.time()]

    def select(timeout: float | None = None) -> Any:
        events = real_select(0)
        if events or timeout is None:
            return events or real_select(None)
        now[0] += max(timeout, 0.0)
        return events

    loop.time = lambda: now[0]  # type: ignore[method-assign]
    selector.select = select
    try:
        yield
    finally:
        del loop.time  # the instance attribute goes: the class's method is back
        del selector.select


def string_frame(topic: str, text: str = "hi", *, no_drop: bool = False, seq: int = 0) -> bytes:
    """A ``std_msgs/msg/String`` frame on *topic*, stamped with the wall clock now."""
    codec = default_codec()
    cls = codec.registry.get(STRING_TYPE).cls
    return codec.encode(cls(text), STRING_TYPE, topic, no_drop=no_drop, seq=seq,
                        publish_time_ns=time.time_ns())


def compressed_frame(topic: str, *, codec: int, original_bytes: int, payload: bytes,
                     seq: int = 0) -> bytes:
    """A ``fleetctl_msgs/msg/Compressed`` frame with arbitrary (possibly hostile) content."""
    wire = default_codec()
    cls = wire.registry.get(COMPRESSED_TYPE).cls
    msg = cls(codec, original_bytes, np.frombuffer(payload, dtype=np.uint8))
    return wire.encode(msg, COMPRESSED_TYPE, topic, seq=seq)


def decode_text(frame: bytes) -> str:
    """The text of a ``std_msgs/msg/String`` frame."""
    _meta, msg = default_codec().decode(frame)
    return str(msg.data)


def watch_reads(monkeypatch: Any,
                connection_class: type[asyncio.Protocol]) -> Callable[[], bool]:
    """Wrap *connection_class*'s ``data_received``; the returned callable says whether the
    caller runs inside one (a frame handed over in the read that brought it)."""
    reading = [False]
    real = connection_class.data_received

    def data_received(self: Any, data: bytes) -> None:
        reading[0] = True
        try:
            real(self, data)
        finally:
            reading[0] = False

    monkeypatch.setattr(connection_class, "data_received", data_received)
    return lambda: reading[0]


async def wait_until(predicate: Callable[[], bool], timeout_s: float) -> None:
    """Poll *predicate* (every 5 ms) on the event loop until true; fail after *timeout_s*."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met before the deadline")
        await asyncio.sleep(0.005)


def wait_for_value(condition: Callable[[], Any], timeout_s: float) -> Any:
    """Poll *condition* (every 20 ms, blocking) until truthy; return its value."""
    deadline = time.monotonic() + timeout_s
    while not (result := condition()):
        assert time.monotonic() < deadline, "condition not met before the deadline"
        time.sleep(0.02)  # polling interval of a deadline-bounded wait
    return result


def _thread_states(pid: int) -> list[str]:
    """The state letter (``R``, ``S``, ``T``, ...) of each thread of process *pid*."""
    states = []
    for stat in Path(f"/proc/{pid}/task").glob("*/stat"):
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            text = stat.read_text()
            states.append(text[text.rindex(")") + 2])  # the field after "(comm)"
    return states


@contextlib.contextmanager
def paused(pid: int, timeout_s: float = 10.0) -> Iterator[None]:
    """Process *pid* stopped (SIGSTOP) while the block runs, continued (SIGCONT) after.

    ``kill(SIGSTOP)`` returns before the process has stopped: the kernel wakes one of its
    threads to stop the others, and until it has run, the others run on (a loaded 2-core
    host took up to 0.4 s to stop every thread of a nats-server, which answered a request
    meanwhile). So the block starts only once every thread is stopped (Linux's ``/proc``).

    Raises:
        AssertionError: Not every thread stopped within *timeout_s*.
    """
    os.kill(pid, signal.SIGSTOP)
    try:
        deadline = time.monotonic() + timeout_s
        while any(state != "T" for state in _thread_states(pid)):
            assert time.monotonic() < deadline, f"process {pid} not stopped in {timeout_s} s"
            time.sleep(0.001)  # polling interval of a deadline-bounded wait
        yield
    finally:
        os.kill(pid, signal.SIGCONT)


def ros_domain_alone(preferred: int, spares: Iterable[int] = SPARE_ROS_DOMAINS) -> int:
    """A ROS domain that no other caller of this function holds: *preferred* if free,
    else the first free one of *spares*; held until this process exits.

    Why: DDS discovery spans the host, and each test module has a fixed domain. Two runs
    of one module at once (a targeted run beside a CI run) share its domain and topic
    names: each sees the other's publishers and takes its messages (test_qos: two
    publishers on ``/burst``, so no gap could be attributed to one; 6 of 30 runs failed).
    The hold is an exclusive ``flock`` on a file per domain in the temporary directory,
    which the kernel drops when the process ends, however it ends.

    Raises:
        RuntimeError: Every one of those domains is held.
    """
    for domain in (preferred, *spares):
        lock = (Path(tempfile.gettempdir()) / f"fleetctl-tests-ros-domain-{domain}.lock"
                ).open("a")
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.close()
            continue
        _HELD_DOMAINS.append(lock)
        return domain
    raise RuntimeError(f"ROS domains {preferred} and {list(spares)} are all held by other "
                       "processes")
