"""fleetctl.gilswitch: the switch interval is lowered to its value, never raised."""

from __future__ import annotations

import sys
from collections.abc import Iterator

import pytest

from fleetctl.gilswitch import GIL_SWITCH_INTERVAL_S, tune_gil


@pytest.fixture(autouse=True)
def _restored() -> Iterator[None]:
    before = sys.getswitchinterval()
    yield
    sys.setswitchinterval(before)


def test_the_default_interval_is_lowered() -> None:
    sys.setswitchinterval(0.005)
    tune_gil()
    assert sys.getswitchinterval() == GIL_SWITCH_INTERVAL_S


def test_a_shorter_interval_is_kept() -> None:
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S / 5)
    tune_gil()
    assert sys.getswitchinterval() == pytest.approx(GIL_SWITCH_INTERVAL_S / 5)
