"""Issue 14, item 1 and the bad-input low items: a bad upgrade request costs the server
nothing it keeps, and no traceback."""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable

import pytest

from fleetctl.server import app
from fleetctl.server.app import RelayServer
from fleetctl.tokens import hash_token, is_wellformed_token
from tests.security.conftest import RawClient
from tests.server.conftest import ALICE_TOKEN, client, next_json, subscribe, wait_for


def no_tracebacks(caplog: pytest.LogCaptureFixture) -> None:
    assert not [r for r in caplog.records if r.exc_info], [r.getMessage() for r in caplog.records]


@pytest.mark.parametrize("header", [
    b"Authorization: Bearer \xff\r\n",
    b"Authorization: Bearer caf\xc3\xa9\r\n",
])
async def test_non_ascii_bearer_token_is_a_bad_token(
    server: RelayServer, header: bytes, caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO)
    for _ in range(50):
        raw = await RawClient.open(server.port)
        assert await raw.request(header) == 101
        assert await raw.close_code() == 4401
        raw.close()
    await wait_for(lambda: server.metrics.connections_open == 0 and not server.core.peers)
    no_tracebacks(caplog)


async def test_repeated_authorization_headers_are_refused_and_leave_nothing(
    server: RelayServer, caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO)
    twice = (f"Authorization: Bearer {ALICE_TOKEN}\r\n" * 2).encode()
    for path in (b"/", b"/robots", b"/metrics"):
        for _ in range(100 if path == b"/" else 1):
            raw = await RawClient.open(server.port)
            assert await raw.request(twice, upgrade=path == b"/", path=path) == 400
            raw.close()
    assert server.metrics.connections_open == 0 and not server.core.peers
    assert server.metrics.connections_total == 0  # refused before any record was made
    no_tracebacks(caplog)


async def test_bad_token_on_http_endpoints_is_401(server: RelayServer) -> None:
    raw = await RawClient.open(server.port)
    assert await raw.request(b"Authorization: Bearer \xff\r\n", upgrade=False,
                             path=b"/robots") == 401
    raw.close()


@pytest.mark.parametrize("token", ["\ud800", "caf\u00e9", "x" * 5000, 12, "", None])
async def test_token_frames_that_cannot_be_tokens_get_4401(server: RelayServer,
                                                           token: object) -> None:
    async with client(server, source="127.0.0.9") as ws:
        await ws.send(json.dumps({"token": token}))
        err = await next_json(ws, "error")
        assert err["code"] in ("bad_token", "malformed_frame")
    await wait_for(lambda: not server.core.peers)


async def test_deeply_nested_json_gets_an_error_frame_only(
    server: RelayServer, caplog: pytest.LogCaptureFixture,
) -> None:
    async with client(server, token=ALICE_TOKEN) as ws:
        await next_json(ws, "welcome")
        for text in ("[" * 4000 + "]" * 4000, '{"a":' * 2000 + "1" + "}" * 2000):
            await ws.send(text)
            assert (await next_json(ws, "error"))["code"] == "malformed_frame"
        assert (await subscribe(ws, "/husky1/.*"))["type"] == "subscribed"  # still open
    no_tracebacks(caplog)


async def test_unknown_paths_and_malformed_requests_are_one_line(
    server: RelayServer, caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO)
    raw = await RawClient.open(server.port)
    assert await raw.request(upgrade=False, path=b"/nope") == 404
    raw.close()
    for method in (b"POST", b"BREW"):
        raw = await RawClient.open(server.port)
        raw.writer.write(method + b" / HTTP/1.1\r\nHost: x\r\n\r\n")
        await raw.reader.read()  # the server hangs up
        raw.close()
    raw = await RawClient.open(server.port)
    raw.writer.write(b"\x16\x03\x01garbage\r\n\r\n")  # a TLS hello on the plain port
    await raw.reader.read()
    raw.close()
    await wait_for(lambda: sum("opening handshake failed" in r.getMessage()
                               for r in caplog.records) >= 3)
    no_tracebacks(caplog)
    lines = [r.getMessage() for r in caplog.records if "handshake failed" in r.getMessage()]
    assert all("\n" not in line for line in lines)
    assert any("unsupported HTTP method" in line for line in lines), lines


def test_token_rule() -> None:
    assert is_wellformed_token("s3cr3t-T0ken_~")
    for bad in ("\ud800", "caf\u00e9", "with space", "", "x" * 1025, None, 5, "tab\t"):
        assert not is_wellformed_token(bad)
    with pytest.raises(UnicodeEncodeError):
        hash_token("\ud800")  # writers' rule unchanged: callers check first


async def test_a_request_sent_too_slowly_is_cut_with_one_line(
    make_server: Callable[..., RelayServer], monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    # Slowloris: websockets cuts an incomplete request at its open_timeout and logs
    # nothing; the cut is now one line (docs/security.md: every refusal says why).
    monkeypatch.setattr(app, "OPEN_TIMEOUT_S", 0.3)
    caplog.set_level(logging.INFO)
    async with make_server() as srv:
        raw = await RawClient.open(srv.port, source="127.0.0.9")
        raw.writer.write(b"GET / HTTP/1.1\r\nHost: x\r\nUpgr")  # and then nothing
        assert await asyncio.wait_for(raw.reader.read(), 5) == b""
        await wait_for(lambda: srv.gate.open == 0)
        silent = await RawClient.open(srv.port, source="127.0.0.9")  # a port scan
        assert await asyncio.wait_for(silent.reader.read(), 5) == b""
        await wait_for(lambda: srv.gate.open == 0)
    lines = [r.getMessage() for r in caplog.records if "incomplete request" in r.getMessage()]
    assert lines == ["opening handshake failed: connection from 127.0.0.9 cut with an "
                     "incomplete request (29 bytes in the handshake timeout)"]
