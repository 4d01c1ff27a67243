"""Session records as replicas write them to the KV bucket: keys and checked values."""

from __future__ import annotations

import pytest

from fleetctl.server.cluster.sessionrecord import (
    MAX_RECORD_BYTES,
    SessionRecord,
    decode_record,
    encode_record,
    parse_record_key,
    record_key,
)


def test_key_round_trip_keeps_every_identity_and_name() -> None:
    key = (("alice@example.com", "ops team"), "console.1")
    text = record_key(key)
    assert "." in text and text.count(".") == 1  # one separator: names are escaped
    assert parse_record_key(text) == key


@pytest.mark.parametrize("text", ["", "alice", "alice.", ".console", "a.b.c", "a=ZZ.b"])
def test_bad_keys_refused(text: str) -> None:
    with pytest.raises(ValueError):
        parse_record_key(text)


def test_value_round_trip() -> None:
    record = SessionRecord(("/husky1/.*", "/husky2/events"), 42, 1764115200.5, "relay-1")
    assert decode_record(encode_record(record)) == record
    offline = SessionRecord((), None, 1.0, None)
    assert decode_record(encode_record(offline)) == offline


@pytest.mark.parametrize(("value", "field"), [
    (b"not json", "JSON"),
    (b"[]", "version 1"),
    (b'{"v": 2}', "version 1"),
    (b'{"v": 1, "patterns": "x", "cursor": null, "since": 1, "owner": null}', "patterns"),
    (b'{"v": 1, "patterns": [1], "cursor": null, "since": 1, "owner": null}', "patterns"),
    (b'{"v": 1, "patterns": [], "cursor": -1, "since": 1, "owner": null}', "cursor"),
    (b'{"v": 1, "patterns": [], "cursor": true, "since": 1, "owner": null}', "cursor"),
    (b'{"v": 1, "patterns": [], "cursor": 1.5, "since": 1, "owner": null}', "cursor"),
    (b'{"v": 1, "patterns": [], "cursor": 1, "since": "now", "owner": null}', "since"),
    (b'{"v": 1, "patterns": [], "cursor": 1, "since": NaN, "owner": null}', "since"),
    (b'{"v": 1, "patterns": [], "cursor": 1, "since": 1, "owner": 7}', "owner"),
    (b"[" * 100_000, "JSON"),
    (b" " * (MAX_RECORD_BYTES + 1), "bytes"),
])
def test_bad_values_refused_naming_the_field(value: bytes, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        decode_record(value)
