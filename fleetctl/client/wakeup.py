"""A set/clear flag the send loop waits on with a timeout, without a task per wait.

``asyncio.wait_for(event.wait(), timeout)`` wraps the wait in a new task on every call
(Python 3.11): a task object, a scheduling round to start it, a timer and a cancellation,
each time the send loop goes idle, which it does once or twice per message. Here a wait is
one future and one timer handle.
"""

from __future__ import annotations

import asyncio


class Wakeup:
    """Like :class:`asyncio.Event` with a timed wait; use it from its loop's thread only."""

    def __init__(self) -> None:
        self._set = False
        self._waiter: asyncio.Future[None] | None = None

    def set(self) -> None:
        """Set the flag and wake the waiter, if any."""
        self._set = True
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    def clear(self) -> None:
        """Clear the flag."""
        self._set = False

    def is_set(self) -> bool:
        """True when set and not cleared since."""
        return self._set

    async def wait(self, timeout_s: float) -> bool:
        """Wait until set or *timeout_s* seconds passed; True when set.

        Raises:
            RuntimeError: Another coroutine is already waiting (one waiter only).
        """
        if self._set:
            return True
        if self._waiter is not None:
            raise RuntimeError("Wakeup supports one waiter at a time")
        loop = asyncio.get_running_loop()
        waiter = self._waiter = loop.create_future()
        timer = loop.call_later(timeout_s, _expire, waiter)
        try:
            await waiter
        finally:
            timer.cancel()
            self._waiter = None
        return self._set


def _expire(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_result(None)
