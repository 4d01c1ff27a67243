"""Server-to-client text frames and close codes (docs/design.md section 2), and the thin
adapters over :mod:`fleetctl.wire.control` the relay uses for control messages.
"""

from __future__ import annotations

import json

from fleetctl.server.permissions import Permissions
from fleetctl.wire import control
from fleetctl.wire.errors import WireError

CLOSE_TOO_BIG = 1009  # frame over max_frame_bytes (websockets sends it for us)
CLOSE_MALFORMED = 1007  # too many malformed frames in a row
CLOSE_BAD_SESSION = 4400  # bad session name, or one session too many for the identity
CLOSE_BAD_TOKEN = 4401
CLOSE_NO_IDENTITY = 4403
CLOSE_SESSION_TAKEN_OVER = 4409  # a newer connection attached to the same session
CLOSE_SUBSCRIPTION_FLOOD = 4429  # refused control requests past the flood bound
CLOSE_TOO_MANY = 4429  # the identity is at max_connections_per_identity
CLOSE_LOGINS_THROTTLED = 4429  # a token from an address over its failed-login budget
CLOSE_GOING_AWAY = 1001  # server shutdown

# Why: client text frames are tiny JSON requests; refuse to parse anything large.
MAX_TEXT_CHARS = 4096

ERROR_CODES = (
    "unauthorized_send",
    "subscription_refused",
    "bad_regex",
    "malformed_frame",
    "unknown_type",
    "too_many_subscriptions",
    "bad_token",
    "bad_session",
    "rate_limited",
    "keyframe_refused",
    "standby",  # a binary frame on a standby connection (discarded)
    "not_standby",  # {"type": "activate"} on a connection that is not a standby
    "login_throttled",  # a token refused unhashed: too many failed logins from the address
    "resume_throttled",  # a session resume while the identity owes first-frame work
)


def welcome(perms: Permissions) -> str:
    """The ``welcome`` frame: identity names and the rules they grant."""
    return json.dumps(
        {
            "type": "welcome",
            "identities": perms.names,
            "rules": [r.as_json() for r in perms.rules],
        }
    )


def error(code: str, topic: str | None, message: str) -> str:
    """An ``error`` frame; *code* is one of :data:`ERROR_CODES`."""
    assert code in ERROR_CODES, code
    return json.dumps({"type": "error", "code": code, "topic": topic, "message": message})


def session(name: str, resumed: bool, mailbox_frames: int, patterns: list[str]) -> str:
    """The ``session`` frame, sent after ``welcome`` to a connection that named a session.

    Args:
        name: The session name.
        resumed: Whether the session existed (its mailbox and subscriptions follow).
        mailbox_frames: no_drop frames queued from the mailbox, ahead of live frames.
        patterns: Subscriptions reinstated from the session (each also gets a
            ``subscribed`` frame).
    """
    return json.dumps({"type": "session", "name": name, "resumed": resumed,
                       "mailbox_frames": mailbox_frames, "subscriptions": patterns})


def ack(kind: str, topic_regex: str) -> str:
    """A ``subscribed`` / ``unsubscribed`` frame."""
    return json.dumps({"type": kind, "topic_regex": topic_regex})


def decode_subscription_fields(frame: bytes) -> tuple[str, bool] | None:
    """Return ``(topic_regex, subscribe)`` of a RobofleetSubscription frame, or ``None``."""
    try:
        sub = control.decode_subscription(frame)
    except WireError:
        return None
    return sub.topic_regex, sub.subscribe


def decode_status_fields(frame: bytes) -> tuple[str, bool, float, str] | None:
    """Return ``(status, is_ok, battery_level, location)`` of a RobofleetStatus frame."""
    try:
        st = control.decode_status(frame)
    except WireError:
        return None
    return st.status, st.is_ok, st.battery_level, st.location
