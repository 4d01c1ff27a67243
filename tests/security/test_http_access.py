"""Issue 14, item 5 and the low items on /robots, identity names and webviz threads."""

from __future__ import annotations

import ipaddress
import logging
from collections.abc import Callable
from typing import Any

import pytest

from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import clean_name
from tests.security.conftest import RawClient
from tests.server.conftest import AUTH, BOB_TOKEN, auth_map, client, next_json, sha


async def get(port: int, path: bytes, extra: bytes = b"", source: str = "127.0.0.1") -> int:
    raw = await RawClient.open(port, source=source)
    try:
        return await raw.request(extra, upgrade=False, path=path)
    finally:
        raw.close()


async def body(port: int, path: str) -> str:
    from tests.server.test_app import http_get
    status, text = await http_get(port, path)
    assert status == 200
    return text


async def test_metrics_needs_loopback_or_an_identity(
    make_server: Callable[..., RelayServer],
) -> None:
    # Tests connect from 127.0.0.x; a trusted proxy header stands for a remote caller.
    async with make_server(trusted_proxies=(ipaddress.ip_network("127.0.0.1/32"),)) as srv:
        remote = b"X-Forwarded-For: 203.0.113.9\r\n"
        bearer = f"Authorization: Bearer {BOB_TOKEN}\r\n".encode()
        assert await get(srv.port, b"/metrics", remote) == 401
        assert await get(srv.port, b"/metrics", remote + b"Authorization: Bearer no\r\n") == 401
        assert await get(srv.port, b"/metrics", remote + bearer) == 200
        assert await get(srv.port, b"/metrics", b"X-Forwarded-For: 127.0.0.2\r\n") == 200
        assert await get(srv.port, b"/metrics") == 200  # the operator on the host


async def test_metrics_labels_name_no_person_and_no_address(server: RelayServer) -> None:
    async with client(server, token=BOB_TOKEN) as bob, client(server, source="127.0.0.2") as r:
        await next_json(bob, "welcome")
        await next_json(r, "welcome")
        text = await body(server.port, "/metrics")
    assert 'connection="conn#' in text
    for secret in ("bob", "husky1", "127.0.0.2"):
        assert secret not in text


@pytest.mark.parametrize("header", [b"X-Forwarded-For: 203.0.113.9\r\n",
                                    b"Forwarded: for=203.0.113.9\r\n",
                                    b"X-Real-IP: 203.0.113.9\r\n"])
async def test_proxy_header_from_untrusted_loopback_gets_no_privilege(
    server: RelayServer, header: bytes, caplog: pytest.LogCaptureFixture,
) -> None:
    assert await get(server.port, b"/robots", header) == 401
    assert await get(server.port, b"/metrics", header) == 401
    assert await get(server.port, b"/robots", header) == 401
    warnings = [r for r in caplog.records if "trusted_proxies" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].levelno == logging.WARNING  # once


async def test_trusted_same_host_proxy_still_works(
    make_server: Callable[..., RelayServer],
) -> None:
    proxies = (ipaddress.ip_network("127.0.0.1/32"),)
    async with make_server(trusted_proxies=proxies) as srv:
        # Behind the proxy: the client's address counts, loopback or not.
        assert await get(srv.port, b"/robots", b"X-Forwarded-For: 203.0.113.9\r\n") == 401
        assert await get(srv.port, b"/robots", b"X-Forwarded-For: 127.0.0.1\r\n") == 200


async def test_any_identity_name_is_served(make_server: Callable[..., RelayServer]) -> None:
    """An emoji e-mail written as JSON surrogate escapes (read back as two lone
    surrogates) must not break /metrics, logs or the session table."""
    raw: dict[str, Any] = {**AUTH, "identities": [
        *AUTH["identities"],
        {"name": "\ud83d\ude00@example.com\udc80", "token_sha256": sha("emoji-token"),
         "rules": [{"topic": ".*", "op": "receive"}]},
    ]}
    auth = auth_map(raw)
    assert auth.identities[-1].name == "\U0001f600@example.com\\udc80"
    session = {"X-Fleetctl-Session": "tab1"}
    async with make_server(auth=auth) as srv, \
            client(srv, token="emoji-token", additional_headers=session) as ws:
        welcome = await next_json(ws, "welcome")
        assert welcome["identities"] == ["\U0001f600@example.com\\udc80"]
        await body(srv.port, "/metrics")


def test_clean_name() -> None:
    assert clean_name("plain@example.com") == "plain@example.com"
    assert clean_name("\ud83d\ude00") == "\U0001f600"
    assert clean_name("a\ud800b").encode("utf-8")  # no lone surrogate left
