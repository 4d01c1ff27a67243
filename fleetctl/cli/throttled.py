"""The CLI's one error for a token the server refused for now: too many failed logins
from this address (HTTP 429, close 4429 ``login_throttled``; docs/security.md).

Every command that presents a token (``recordings``, ``foxglove-url``, ``replay``) says
it the same way, in one line, with the wait the server asked for, and exits 7
(:attr:`~fleetctl.errors.ExitCode.RETRY_LATER`): a script can tell "come back in N s"
from "your token is wrong" (exit 3). The command does not wait and retry by itself: a
person at a terminal wants to know now, and whoever keeps failing behind the same
address is theirs to find.
"""

from __future__ import annotations

from fleetctl.client.loginthrottle import EXPLANATION, LoginThrottled
from fleetctl.errors import RetryLater


def throttled_error(what: str, throttle: LoginThrottled) -> RetryLater:
    """The one-line error for *what* (``URL: GET /path``, ``replay: URL``), without the
    token: why, what to check, and when to try again."""
    how = "429" if throttle.where == "upgrade" else "close 4429"
    return RetryLater(f"{what}: refused for now ({how}): {EXPLANATION}; check --token-file "
                      f"and the other clients there, then {throttle.retry_text()}",
                      throttle.retry_after_s)
