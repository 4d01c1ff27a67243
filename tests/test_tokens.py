"""The token storage rule, checked against an independent SHA-256 value."""

from __future__ import annotations

from fleetctl.tokens import hash_token


def test_hash_is_hex_sha256_of_utf8() -> None:
    # sha256(b"test"), a published test vector
    expected = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"
    assert hash_token("test") == expected
