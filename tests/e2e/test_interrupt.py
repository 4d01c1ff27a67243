"""Signals raise Interrupted while a SignalGuard is active; cleanup blocks defer them."""

from __future__ import annotations

import os
import signal

import pytest

from fleetctl.e2e.interrupt import SIGNALS, Interrupted, SignalGuard, deferred


@pytest.mark.parametrize("signum", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_a_signal_raises_interrupted_and_the_handlers_come_back(signum: int) -> None:
    before = signal.getsignal(signum)
    with pytest.raises(Interrupted) as info, SignalGuard():
        os.kill(os.getpid(), signum)  # delivered to this (main) thread before kill returns
    assert info.value.signum == signum
    assert info.value.shell_status == 128 + signum
    assert str(info.value) == f"interrupted by {signal.Signals(signum).name}"
    assert signal.getsignal(signum) is before


def test_interrupted_is_not_an_exception_the_scenarios_could_swallow() -> None:
    assert not issubclass(Interrupted, Exception)


def test_a_signal_inside_a_cleanup_block_is_raised_after_it() -> None:
    done = []
    with pytest.raises(Interrupted), SignalGuard():
        with deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            done.append("cleanup ran to the end")
        done.append("not reached")
    assert done == ["cleanup ran to the end"]


def test_later_signals_do_not_interrupt_the_unwinding() -> None:
    steps = []
    with pytest.raises(Interrupted) as info, SignalGuard():
        try:
            os.kill(os.getpid(), signal.SIGINT)
        finally:
            with deferred():
                os.kill(os.getpid(), signal.SIGTERM)  # a second Ctrl-C / kill: ignored
                steps.append("cleanup")
    assert steps == ["cleanup"]
    assert info.value.signum == signal.SIGINT


def test_deferred_without_a_guard_does_nothing() -> None:
    with deferred():
        pass
