"""The robot's wall clock against its server's Date header."""

from __future__ import annotations

from email.utils import formatdate

import pytest

from fleetctl.client.clockcheck import ClockCheck, clock_line, date_offset_s

SERVER_S = 1_796_540_000.0  # a whole second, as Date says it


def date(at_s: float) -> str:
    return formatdate(at_s, usegmt=True)


@pytest.mark.parametrize(("robot_s", "offset"), [
    (SERVER_S, 0.0), (SERVER_S + 0.99, 0.0),  # in step: Date is truncated to the second
    (SERVER_S + 1.9, 0.0), (SERVER_S - 0.9, 0.0),  # ... a round trip, a small offset
    (SERVER_S + 2.5, 2.0), (SERVER_S - 1.5, -2.0),
    (SERVER_S - 3600.0, -3600.5), (SERVER_S - 3599.01, -3599.51)])
def test_the_offset_is_read_from_the_middle_of_the_dates_second(
        robot_s: float, offset: float) -> None:
    assert date_offset_s(date(SERVER_S), robot_s) == pytest.approx(offset)


@pytest.mark.parametrize("header", [None, "", "yesterday", "Sun, 06 Dec 2026 07:34:36 -0000"])
def test_no_readable_date_is_no_reading(header: str | None) -> None:
    assert date_offset_s(header, SERVER_S) is None
    assert ClockCheck().reading(header, SERVER_S) is None


def test_an_offset_is_said_once_and_its_end_once() -> None:
    check = ClockCheck()
    assert check.reading(date(SERVER_S), SERVER_S + 0.3) is None
    assert check.reading(date(SERVER_S), SERVER_S - 3600.0) == ("off", -3600.5)
    assert check.reading(date(SERVER_S), SERVER_S - 3600.0) is None  # said already
    assert check.offset_s == -3600.5
    assert check.reading(date(SERVER_S), SERVER_S + 0.5) == ("agrees", 0.0)
    assert check.reading(date(SERVER_S), SERVER_S + 0.5) is None
    assert check.offset_s == 0.0


def test_the_line_says_which_way_and_what_the_pages_show() -> None:
    assert clock_line("off", -3600.4, "ws://10.8.0.1:8080/") == (
        "this robot's wall clock is about 3600 s behind ws://10.8.0.1:8080/'s (the Date of its "
        "upgrade answer): frames carry the robot's clock, so the fleet's pages show its live "
        "data as about 3600 s old; sync it (chrony or systemd-timesyncd; a robot without "
        "internet can use the fleet machine as its NTP server)")
    assert "ahead of ws://h/'s" in clock_line("off", 90.0, "ws://h/")
    assert "stamped about 90 s in the future" in clock_line("off", 90.0, "ws://h/")
