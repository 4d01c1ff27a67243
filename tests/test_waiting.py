"""The project's deadline-bounded wait."""

from __future__ import annotations

import pytest

from fleetctl.errors import FleetError
from fleetctl.waiting import wait_until


def test_wait_until_times_out_with_a_named_condition() -> None:
    with pytest.raises(FleetError, match="the impossible"):
        wait_until(lambda: False, 0.2, poll_s=0.05, describe="the impossible")


def test_wait_until_returns_once_the_condition_holds() -> None:
    calls = iter([False, False, True])
    wait_until(lambda: next(calls), 5.0, poll_s=0.001, describe="third call")


def test_wait_until_raises_the_callers_error_at_the_deadline() -> None:
    """A caller that knows more at the deadline (what it still waits for) says it."""
    with pytest.raises(FleetError, match="server: still starting"):
        wait_until(lambda: False, 0.05, poll_s=0.01, describe="never",
                   timeout_error=lambda: FleetError("server: still starting"))
