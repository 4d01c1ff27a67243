"""Recognise the relay's failed-login throttle and how long it asks a client to wait.

The relay keeps a failed-login budget per source address (an IPv4 address, an IPv6 /64;
:mod:`fleetctl.server.loginbudget`, docs/security.md "Failed logins"). Past it, a token is
refused before it is hashed:

- at the HTTP upgrade (or a plain GET) with **429** and ``Retry-After`` in whole seconds
  (RFC 9110 15.5.20 and 10.2.3);
- after a ``{"token": ...}`` frame with an error frame of code ``login_throttled``, then
  the close **4429** whose reason is the same message, ``too many failed logins from this
  address: retry in N s``.

4429 alone is not enough: the relay also closes with 4429 for too many connections of
one identity and for a subscription flood; only the reason (or the error frame before
it) says which. The server is reachable in every case: a client that says "cannot
connect" sends its operator to the network instead of to the token.

Pure functions; the robot link (:mod:`fleetctl.client.transport`), the CLI's HTTP
requests (:mod:`fleetctl.cli.recordings`) and ``replay`` act on what they return.
"""

from __future__ import annotations

import email.utils
import math
import re
from dataclasses import dataclass
from typing import Protocol

TOO_MANY_REQUESTS = 429
CLOSE_LOGIN_THROTTLED = 4429  # fleetctl.server.protocol.CLOSE_LOGINS_THROTTLED
ERROR_CODE = "login_throttled"  # the error frame's code before that close
# The relay's message, in the 429's body, the error frame and the close reason.
_MESSAGE = re.compile(r"too many failed logins from this address: retry in ([0-9]{1,9}) s")
# Why a cap: our relay never asks for more than its refill interval (2 s), but a reverse
# proxy's rate limiter or a confused server may say an hour; a robot out of contact that
# long because of one header is worse than one more refused upgrade (which costs the
# relay no hash) every 5 minutes.
MAX_RETRY_AFTER_S = 300.0

# What the client's operator should know, said once per throttled spell.
EXPLANATION = ("too many failed logins from this address (the server's failed-login "
               "budget per IPv4 address or IPv6 /64: 20, then one per 2 s): a wrong token "
               "here, or on another client behind the same address or NAT")


class Headers(Protocol):
    """Response headers, looked up case-insensitively (websockets' ``Headers``,
    ``email.message.Message`` as urllib's ``HTTPError.headers``)."""

    def get(self, name: str, /) -> str | None:
        """The first value of header *name*, or ``None``."""
        ...


@dataclass(frozen=True)
class LoginThrottled:
    """The relay refused a token unhashed: too many failed logins from this address.

    Attributes:
        retry_after_s: Seconds the server asked the client to wait (``Retry-After``, or
            the close reason's ``retry in N s``), capped at :data:`MAX_RETRY_AFTER_S`;
            ``None`` when it said nothing usable (the caller's normal backoff applies).
        where: ``"upgrade"`` (HTTP 429) or ``"token frame"`` (close 4429).
    """

    retry_after_s: float | None
    where: str

    def retry_text(self) -> str:
        """``"retry in N s"``, or ``"retry later"`` without a hint."""
        if self.retry_after_s is None:
            return "retry later"
        return f"retry in {math.ceil(self.retry_after_s):d} s"


def parse_retry_after(value: str | None, now_wall_s: float | None = None) -> float | None:
    """A ``Retry-After`` header's wait in seconds, capped at :data:`MAX_RETRY_AFTER_S`.

    Args:
        value: The header's value: delay-seconds (ASCII digits) or an HTTP-date (RFC
            9110 10.2.3; a proxy may send one). ``None``: no header.
        now_wall_s: The wall clock (seconds since the epoch) an HTTP-date is measured
            from; ``None``: an HTTP-date is not read.

    Returns:
        Seconds to wait (0 for a date in the past), or ``None`` for a missing or
        unreadable value (negative, not digits, not a date).
    """
    if value is None:
        return None
    text = value.strip()
    if re.fullmatch(r"[0-9]{1,9}", text):
        return min(float(text), MAX_RETRY_AFTER_S)
    if now_wall_s is None:
        return None
    try:
        when = email.utils.parsedate_to_datetime(text)
    except (TypeError, ValueError, IndexError):
        return None
    if when.tzinfo is None:  # RFC 9110 5.6.7: an HTTP-date is GMT
        return None
    return min(max(0.0, when.timestamp() - now_wall_s), MAX_RETRY_AFTER_S)


def retry_after_in_text(text: str) -> float | None:
    """The wait in the relay's ``... retry in N s`` message (seconds, capped), or
    ``None`` when *text* is not that message."""
    match = _MESSAGE.search(text)
    return None if match is None else min(float(match.group(1)), MAX_RETRY_AFTER_S)


def from_response(status: int, headers: Headers,
                  now_wall_s: float | None = None) -> LoginThrottled | None:
    """The throttle an HTTP answer (to an upgrade or a GET) reports, or ``None``.

    Any 429 counts: only the failed-login budget answers 429 on the relay's listeners
    (a flood of control requests is throttled inside a connection, never at the door).

    Args:
        status: The HTTP status code.
        headers: The response headers.
        now_wall_s: Wall clock for a ``Retry-After`` HTTP-date (see
            :func:`parse_retry_after`).
    """
    if status != TOO_MANY_REQUESTS:
        return None
    return LoginThrottled(parse_retry_after(headers.get("Retry-After"), now_wall_s),
                          "upgrade")


def from_close(code: int, reason: str, error_code: str | None = None) -> LoginThrottled | None:
    """The throttle a close frame reports, or ``None`` (another 4429, another code).

    Args:
        code: The close code.
        reason: The close reason.
        error_code: The code of the error frame the server sent last on this connection
            (``login_throttled`` before this close), or ``None``.
    """
    if code != CLOSE_LOGIN_THROTTLED:
        return None
    wait_s = retry_after_in_text(reason)
    if wait_s is None and error_code != ERROR_CODE:
        return None  # 4429 for too many connections or a subscription flood
    return LoginThrottled(wait_s, "token frame")
