"""Names as JetStream KV key tokens."""

from __future__ import annotations

import re

import pytest

from fleetctl.server.cluster.kvkeys import from_key_token, key_token

KV_KEY = re.compile(r"^[-/_=\.a-zA-Z0-9]+$")  # what NATS KV accepts


@pytest.mark.parametrize("name", ["husky1", "robot.1", "a=b", "é", "with space", "x~y",
                                  "-_-", "日本", "/husky1/map", "a/b.c"])
def test_tokens_are_valid_one_token_and_reversible(name: str) -> None:
    token = key_token(name)
    assert KV_KEY.match(token) and "." not in token and "/" not in token
    assert from_key_token(token) == name


@pytest.mark.parametrize("token", ["a.b", "a/b", "=4", "=ZZ", "a b"])
def test_tokens_it_does_not_make_are_refused(token: str) -> None:
    with pytest.raises(ValueError):
        from_key_token(token)
