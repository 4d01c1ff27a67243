"""``GET /login-budget`` through real sockets: a page on any origin asks whether its
address is over its failed-login budget (docs/security.md, "Failed logins"): 204 or 429
with ``Retry-After``, readable cross-origin, never charging, never hashing a token, and
under the same unauthenticated-connection caps as every other request."""

from __future__ import annotations

import asyncio
import ssl
from collections.abc import Callable
from pathlib import Path

import pytest

from fleetctl.server import loginbudget
from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerLimits, WebConfig
from fleetctl.server.endpoints import LOGIN_BUDGET_PATH
from tests.security.conftest import RawClient
from tests.server.certs import self_signed
from tests.server.conftest import client, wait_for
from tests.server.test_app import closed_code

ORIGIN = "http://page.example:8000"  # the page is served from elsewhere


@pytest.fixture
def small_budget(monkeypatch: pytest.MonkeyPatch) -> None:
    """Three failures per address, then one a minute (the defaults: 20, one per 2 s)."""
    monkeypatch.setattr(loginbudget, "FAILURES_BURST", 3)
    monkeypatch.setattr(loginbudget, "FAILURE_INTERVAL_S", 60.0)


async def probe(port: int, source: str, extra: str = "", tls: ssl.SSLContext | None = None,
                ) -> tuple[int, dict[str, str], bytes]:
    """A browser's cross-origin GET of the probe: status, headers (lower-case), body;
    status 0: the connection was aborted without an answer."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0),
                                                   ssl=tls)
    writer.write(f"GET {LOGIN_BUDGET_PATH} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
                 f"Origin: {ORIGIN}\r\n{extra}\r\n".encode())
    try:
        data = await asyncio.wait_for(reader.read(), 5)
    except ConnectionResetError:
        data = b""
    writer.close()
    if not data:
        return 0, {}, b""  # no answer: the connection was aborted
    head, _, body = data.partition(b"\r\n\r\n")
    status, *lines = head.decode().split("\r\n")
    headers = {k.lower(): v for k, v in (line.split(": ", 1) for line in lines)}
    return int(status.split()[1]), headers, body


def assert_cross_origin(headers: dict[str, str]) -> None:
    assert headers["access-control-allow-origin"] == "*"
    assert headers["access-control-expose-headers"] == "Retry-After"
    assert headers["cache-control"] == "no-store"
    # Nothing a browser would attach to a later request or send credentials for.
    assert "set-cookie" not in headers
    assert "access-control-allow-credentials" not in headers


async def spend_budget(srv: RelayServer, source: str) -> None:
    for _ in range(3):  # a script at *source* with a stale token
        async with client(srv, source=source, token="stale") as ws:
            assert await closed_code(ws) == 4401


@pytest.mark.usefixtures("small_budget")
async def test_the_probe_says_the_callers_own_budget(
        make_server: Callable[..., RelayServer]) -> None:
    async with make_server() as srv:
        status, headers, body = await probe(srv.port, "127.0.0.9")
        assert (status, body) == (204, b"")
        assert_cross_origin(headers)
        assert "retry-after" not in headers and "content-length" not in headers

        await spend_budget(srv, "127.0.0.9")
        status, headers, body = await probe(srv.port, "127.0.0.9")
        assert status == 429 and headers["retry-after"] == "60"
        assert b"too many failed logins" in body and len(body) < 100
        assert_cross_origin(headers)
        # Only the caller's own address: its neighbour is within its budget.
        assert (await probe(srv.port, "127.0.0.10"))[0] == 204
        # Asking is no login: neither a failure nor a refusal, however often.
        for _ in range(5):
            assert (await probe(srv.port, "127.0.0.9"))[0] == 429
        assert (srv.core.logins.failures, srv.core.logins.refusals) == (3, 0)


@pytest.mark.usefixtures("small_budget")
async def test_a_token_on_the_probe_is_never_looked_at(
        make_server: Callable[..., RelayServer]) -> None:
    async with make_server() as srv:
        for _ in range(5):  # wrong tokens: each would have been one failed login
            status, _, _ = await probe(srv.port, "127.0.0.9", "Authorization: Bearer wrong\r\n")
            assert status == 204
        assert srv.core.logins.failures == 0 and "bad_token" not in srv.metrics.errors


@pytest.mark.usefixtures("small_budget")
async def test_the_web_listener_answers_it_too(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:
    cert, key = self_signed(tmp_path / "tls")
    web = WebConfig(tls_cert=cert, tls_key=key, listen_host="127.0.0.1", listen_port=0)
    tls = ssl.create_default_context()
    tls.check_hostname = False
    tls.verify_mode = ssl.CERT_NONE  # the test's self-signed certificate
    async with make_server(web=web) as srv:
        assert (await probe(srv.web_port, "127.0.0.9", tls=tls))[0] == 204
        await spend_budget(srv, "127.0.0.9")  # on the relay port: one budget per address
        status, headers, _ = await probe(srv.web_port, "127.0.0.9", tls=tls)
        assert status == 429 and headers["retry-after"] == "60"
        assert_cross_origin(headers)


async def test_the_probe_takes_an_unauthenticated_slot_like_any_request(
        make_server: Callable[..., RelayServer]) -> None:
    limits = ServerLimits(max_unauthenticated_per_address=2,
                          max_unauthenticated_connections=4)
    async with make_server(limits=limits) as srv:
        held = [await RawClient.open(srv.port, source="127.0.0.9") for _ in range(2)]
        await wait_for(lambda: srv.gate.open == 2)
        assert (await probe(srv.port, "127.0.0.9"))[0] == 0  # aborted at accept
        assert srv.metrics.connections_refused["per_address"] == 1
        assert (await probe(srv.port, "127.0.0.10"))[0] == 204
        for raw in held:
            raw.close()
        await wait_for(lambda: srv.gate.open == 0)
