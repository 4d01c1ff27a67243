"""Wait for a condition with a deadline (the project's one polling loop).

Orchestration code (the demo supervisor, the e2e runs) waits on things it cannot be told
about: a port answering, a file appearing, a container's process exiting. It polls, with a
deadline, and says what it was waiting for when the deadline passes.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from fleetctl.errors import FleetError


def wait_until(
    condition: Callable[[], object],
    timeout_s: float,
    poll_s: float = 0.1,
    describe: str = "condition",
    timeout_error: Callable[[], FleetError] | None = None,
) -> None:
    """Poll ``condition()`` until it is truthy or *timeout_s* passes.

    Args:
        timeout_error: Builds the error raised at the deadline, for a caller that can say
            more than *describe* then (what it still waits for); ``None``: the default.

    Raises:
        FleetError: the deadline passed first (the message names *describe*), or what
            *timeout_error* built; whatever ``condition()`` raises, as it is.
    """
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() >= deadline:
            if timeout_error is not None:
                raise timeout_error()
            raise FleetError(f"timed out after {timeout_s:.0f} s waiting for {describe}")
        time.sleep(poll_s)  # polling interval of a deadline-bounded wait, not synchronization
