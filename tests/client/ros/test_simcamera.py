"""The simulated camera's command line: its size argument."""

from __future__ import annotations

import pytest

pytest.importorskip("rclpy")

from fleetctl.client.ros.simcamera import _size


def test_size_is_width_by_height() -> None:
    assert _size("320x240") == (320, 240)
    assert _size("640X480") == (640, 480)


@pytest.mark.parametrize("text", ["320", "x240", "320x", "0x240", "320x-1", "axb", ""])
def test_a_bad_size_names_the_argument(text: str) -> None:
    with pytest.raises(SystemExit, match="WIDTHxHEIGHT"):
        _size(text)
