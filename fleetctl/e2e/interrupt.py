"""Turn SIGTERM, SIGINT and SIGHUP into an exception, so an interrupted run cleans up.

By default SIGTERM and SIGHUP end a Python process on the spot (no ``finally``, no
``__exit__``), and SIGINT raises :class:`KeyboardInterrupt`, which the CLI would show as a
traceback. ``fleetctl e2e`` owns containers and networks that only its
:class:`~fleetctl.e2e.topology.Topology` context manager removes, so while :class:`SignalGuard`
is active each of these signals raises :class:`Interrupted` in the main thread instead, and the
stack unwinds through every ``with`` block. Like :class:`KeyboardInterrupt` it is a
:class:`BaseException`, so the scenarios' ``except FleetError`` (a component that failed to
start, a baseline that stalled) cannot swallow it and carry on with the next scenario.

Cleanup code runs inside :func:`deferred`: a signal that arrives there is remembered and
raised when the cleanup is done, never in the middle of it. Once one signal has been raised,
later ones are ignored (a second Ctrl-C must not abort the removal the first one started).

Python runs signal handlers in the main thread only, between bytecodes; a blocking call
(``time.sleep``, ``subprocess.run``) is interrupted by the handler's exception, and
``subprocess.run`` then kills the child it was waiting for (so no docker CLI child outlives
the run).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType
from typing import Any

SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)


class Interrupted(BaseException):  # like KeyboardInterrupt
    """The run was stopped by a signal; everything it made was (or is being) removed.

    Attributes:
        signum: The signal number.
    """

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f"interrupted by {signal.Signals(signum).name}")

    @property
    def shell_status(self) -> int:
        """The conventional exit status of a process ended by this signal (128 + number)."""
        return 128 + self.signum


class SignalGuard:
    """While active (``with SignalGuard():``), :data:`SIGNALS` raise :class:`Interrupted`.

    Only one guard is active at a time (signal dispositions are per process). Outside the
    main thread it does nothing: Python cannot install handlers there.
    """

    _active: SignalGuard | None = None

    def __init__(self) -> None:
        self.received: int | None = None  # the first signal, if any
        self._raised = False
        self._defer_depth = 0
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> SignalGuard:
        if threading.current_thread() is not threading.main_thread():
            return self
        for signum in SIGNALS:
            self._previous[signum] = signal.signal(signum, self._handle)
        SignalGuard._active = self
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous.clear()
        if SignalGuard._active is self:
            SignalGuard._active = None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.received is not None:
            return  # already unwinding (or about to): the first signal wins
        self.received = signum
        if self._defer_depth == 0:
            self._raise()

    def _raise(self) -> None:
        assert self.received is not None
        self._raised = True
        raise Interrupted(self.received)

    @contextlib.contextmanager
    def deferring(self) -> Iterator[None]:
        """Hold a signal that arrives inside the block until the block is done."""
        self._defer_depth += 1
        try:
            yield
        finally:
            self._defer_depth -= 1
        if self._defer_depth == 0 and self.received is not None and not self._raised:
            self._raise()


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Run a cleanup block without being interrupted by the active guard (if any)."""
    guard = SignalGuard._active
    if guard is None:
        yield
        return
    with guard.deferring():
        yield
