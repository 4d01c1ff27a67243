from __future__ import annotations

import ipaddress

from fleetctl.server.identity import (
    bearer_token,
    effective_address,
    parse_address,
    token_from_frame,
)

PROXIES = (ipaddress.ip_network("10.0.0.1/32"), ipaddress.ip_network("10.1.0.0/16"))


def test_forwarded_for_only_from_trusted_proxies() -> None:
    peer = parse_address("10.0.0.1")
    assert effective_address(peer, "10.8.0.2", PROXIES) == parse_address("10.8.0.2")
    untrusted = parse_address("192.168.1.5")
    assert effective_address(untrusted, "10.8.0.2", PROXIES) == untrusted
    # Left-most entries are client-written: take the nearest hop that is not a proxy.
    assert effective_address(peer, "1.1.1.1, 10.8.0.2, 10.1.2.3", PROXIES) == parse_address(
        "10.8.0.2")
    assert effective_address(peer, "garbage", PROXIES) is None
    assert effective_address(peer, None, PROXIES) == peer


def test_parse_address_maps_ipv4_in_ipv6() -> None:
    assert parse_address("::ffff:127.0.0.2") == ipaddress.ip_address("127.0.0.2")
    assert parse_address("nope") is None and parse_address(None) is None


def test_bearer_and_token_frame() -> None:
    assert bearer_token("Bearer abc") == "abc"
    assert bearer_token("bearer  abc ") == "abc"
    assert bearer_token("Basic abc") is None and bearer_token("Bearer ") is None
    assert token_from_frame('{"token": "t"}') == "t"
    assert token_from_frame('{"token": 3}') is None
    assert token_from_frame("[1]") is None and token_from_frame("{") is None
    assert token_from_frame('{"token": "' + "x" * 5000 + '"}') is None
