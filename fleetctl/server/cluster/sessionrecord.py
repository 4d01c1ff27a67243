"""A named session as replicas share it: one JetStream KV entry per session (issue 15).

Key: the session key ``(identities, name)`` as ``<identity>/<identity>.<name>``, each part
one KV token (:func:`~fleetctl.server.cluster.kvkeys.key_token`).

Value: JSON (written once a second at most per session, never per frame)::

    {"v": 1, "patterns": ["/husky1/cmd"], "cursor": 1234, "since": 1764115200.5,
     "owner": "relay-1"}

- ``cursor``: the no_drop stream's sequence up to which the session's connection has
  acknowledged every frame meant for it (``null``: none yet);
- ``since``: wall-clock time the session began (the stream is replayed from there while
  ``cursor`` is ``null``);
- ``owner``: the replica the session's connection is attached to, ``null`` while offline.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

from fleetctl.server.cluster.kvkeys import from_key_token, key_token

SessionKey = tuple[tuple[str, ...], str]
VERSION = 1
# A record is small: patterns are bounded by max_subscriptions_per_connection and the
# per-connection pattern bytes; anything bigger was not written by a replica.
MAX_RECORD_BYTES = 256 * 1024


@dataclass(frozen=True)
class SessionRecord:
    """What the replicas know of one session.

    Attributes:
        patterns: Subscription regexes, in subscription order.
        cursor: Last acknowledged stream sequence, or ``None``.
        since: Wall-clock seconds when the session began.
        owner: Replica holding its connection, or ``None`` (offline).
    """

    patterns: tuple[str, ...]
    cursor: int | None
    since: float
    owner: str | None


def record_key(key: SessionKey) -> str:
    """The KV key of session *key*."""
    identities, name = key
    return "/".join(key_token(i) for i in identities) + "." + key_token(name)


def parse_record_key(text: str) -> SessionKey:
    """The inverse of :func:`record_key`.

    Raises:
        ValueError: Not a key :func:`record_key` makes.
    """
    ids, dot, name = text.partition(".")
    if not dot or not ids or not name or "." in name:
        raise ValueError(f"bad session key {text!r}")
    try:
        return tuple(from_key_token(i) for i in ids.split("/")), from_key_token(name)
    except UnicodeDecodeError as exc:
        raise ValueError(f"bad session key {text!r}") from exc


def encode_record(record: SessionRecord) -> bytes:
    return json.dumps({"v": VERSION, "patterns": list(record.patterns),
                       "cursor": record.cursor, "since": record.since,
                       "owner": record.owner}, separators=(",", ":")).encode()


def decode_record(value: bytes) -> SessionRecord:
    """A record, checked field by field (anyone with bucket access may have written it).

    Raises:
        ValueError: Not a record :func:`encode_record` makes (the message says which field).
    """
    if len(value) > MAX_RECORD_BYTES:
        raise ValueError(f"record of {len(value)} bytes")
    try:
        data: Any = json.loads(value)
    except (ValueError, RecursionError) as exc:
        raise ValueError("record is not JSON") from exc
    if not isinstance(data, dict) or data.get("v") != VERSION:
        raise ValueError("record is not a version 1 object")
    patterns = data.get("patterns")
    if not isinstance(patterns, list) or not all(isinstance(p, str) for p in patterns):
        raise ValueError("field 'patterns' is not a list of strings")
    cursor = data.get("cursor")
    if cursor is not None and (isinstance(cursor, bool) or not isinstance(cursor, int)
                               or cursor < 0):
        raise ValueError("field 'cursor' is not a sequence number")
    since = data.get("since")
    if isinstance(since, bool) or not isinstance(since, (int, float)) \
            or not math.isfinite(since):
        raise ValueError("field 'since' is not a time")
    owner = data.get("owner")
    if owner is not None and not isinstance(owner, str):
        raise ValueError("field 'owner' is not a replica name")
    return SessionRecord(tuple(patterns), cursor, float(since), owner)
