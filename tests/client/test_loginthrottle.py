"""fleetctl.client.loginthrottle: Retry-After and the relay's throttled close, read."""

from __future__ import annotations

import email.utils

import pytest

from fleetctl.client.loginthrottle import (
    MAX_RETRY_AFTER_S,
    LoginThrottled,
    from_close,
    from_response,
    parse_retry_after,
    retry_after_in_text,
)

NOW = 1_800_000_000.0  # a wall clock, seconds since the epoch


@pytest.mark.parametrize(("value", "seconds"), [
    ("2", 2.0), (" 17 ", 17.0), ("0", 0.0),
    ("86400", MAX_RETRY_AFTER_S),  # a proxy's hour: capped
    (None, None), ("", None), ("-3", None), ("2.5", None), ("soon", None),
    ("\uff12", None),  # a full-width digit is not delay-seconds
    ("9999999999", None),  # more digits than anyone means
])
def test_delay_seconds(value: str | None, seconds: float | None) -> None:
    assert parse_retry_after(value, NOW) == seconds


def test_an_http_date_counts_from_the_wall_clock() -> None:
    in_a_minute = email.utils.formatdate(NOW + 60.0, usegmt=True)
    assert parse_retry_after(in_a_minute, NOW) == pytest.approx(60.0)
    assert parse_retry_after(email.utils.formatdate(NOW - 60.0, usegmt=True), NOW) == 0.0
    assert parse_retry_after(email.utils.formatdate(NOW + 1e6, usegmt=True),
                             NOW) == MAX_RETRY_AFTER_S
    assert parse_retry_after(in_a_minute) is None  # no wall clock given: not read
    assert parse_retry_after("Sun, 06 Dec 2026 99:00:00 GMT", NOW) is None


def test_a_429_is_throttled_whatever_its_header() -> None:
    assert from_response(429, {"Retry-After": "2"}) == LoginThrottled(2.0, "upgrade")
    assert from_response(429, {}) == LoginThrottled(None, "upgrade")  # normal backoff
    assert from_response(429, {"Retry-After": "x"}) == LoginThrottled(None, "upgrade")
    assert from_response(401, {"Retry-After": "2"}) is None


def test_only_the_login_4429_is_throttled() -> None:
    reason = "too many failed logins from this address: retry in 2 s"
    assert from_close(4429, reason) == LoginThrottled(2.0, "token frame")
    assert from_close(4429, "", "login_throttled") == LoginThrottled(None, "token frame")
    # The relay's other 4429s: too many connections, a subscription flood.
    assert from_close(4429, "identity 'x' has 64 connections open") is None
    assert from_close(4429, "too many refused subscriptions", "too_many_subscriptions") is None
    assert from_close(4401, reason) is None
    assert retry_after_in_text("... retry in 99999 s") is None  # not the relay's message


def test_the_retry_text_rounds_up() -> None:
    assert LoginThrottled(1.2, "upgrade").retry_text() == "retry in 2 s"
    assert LoginThrottled(None, "upgrade").retry_text() == "retry later"
