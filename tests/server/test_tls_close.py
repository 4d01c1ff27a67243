"""Closing a TLS connection the relay refuses (a bad token on the web listener) on the
Python the server image runs: Debian bookworm's 3.11.2, whose asyncio TLS transport
forgets its protocol on a second ``close()`` and then raises from ``abort()`` (CPython
gh-98539, guarded from 3.11.4). The relay closed such a connection twice, and every
failed login on the HTTPS port put a 40-line traceback ("Task exception was never
retrieved ... 'NoneType' object has no attribute '_abort'") in the server's log."""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable
from typing import Any

import pytest
from websockets.asyncio.client import connect

from fleetctl.server import connection
from fleetctl.server.app import RelayServer
from fleetctl.server.config import WebConfig
from tests.server.test_listeners import client_tls, web_config  # noqa: F401 (fixture)
from tests.support import wait_until


class BookwormAborts:
    """``_SSLProtocolTransport.abort`` as Python 3.11.2 has it (no check that the
    transport still has its protocol), noting which transports were aborted and which
    of those had lost their protocol to a second ``close()``."""

    def __init__(self) -> None:
        self.aborted: set[int] = set()
        self.orphans: set[int] = set()

    def abort(self, transport: Any) -> None:
        self.aborted.add(id(transport))
        transport._closed = True
        if transport._ssl_protocol is None:
            self.orphans.add(id(transport))
        transport._ssl_protocol._abort()  # raises, as 3.11.2 does, after a second close


@pytest.fixture
def bookworm_ssl_abort(monkeypatch: pytest.MonkeyPatch) -> BookwormAborts:
    from asyncio import sslproto

    aborts = BookwormAborts()
    monkeypatch.setattr(sslproto._SSLProtocolTransport, "abort",
                        lambda transport: aborts.abort(transport))
    monkeypatch.setattr(connection, "ABORT_AFTER_S", 0.05)
    return aborts


async def test_a_refused_login_over_tls_closes_once_and_logs_no_traceback(
    make_server: Callable[..., RelayServer], web_config: WebConfig,  # noqa: F811
    bookworm_ssl_abort: BookwormAborts, caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    refused: list[int] = []  # the relay's transports of the refused logins
    abort_with = connection.RelayConnection.abort_with

    def noting(self: connection.RelayConnection, code: int, reason: str) -> None:
        refused.append(id(self.transport))
        abort_with(self, code, reason)

    monkeypatch.setattr(connection.RelayConnection, "abort_with", noting)
    caplog.set_level(logging.WARNING)
    loop_errors: list[dict[str, Any]] = []
    loop = asyncio.get_running_loop()
    loop.set_exception_handler(lambda _loop, context: loop_errors.append(context))
    async with make_server(web=web_config) as srv:
        url = f"wss://127.0.0.1:{srv.web_port}/"
        for _ in range(3):
            async with connect(url, ssl=client_tls()) as ws:
                await ws.send(json.dumps({"token": "not-a-token-of-this-fleet-at-all"}))
                with pytest.raises(Exception):  # noqa: B017 (the close: 4401)
                    while True:
                        await ws.recv()
                assert ws.close_code == 4401
        # The relay's delayed abort (ABORT_AFTER_S) of each refused connection has run.
        await wait_until(lambda: len(refused) == 3
                         and set(refused) <= bookworm_ssl_abort.aborted, timeout_s=5)
    assert bookworm_ssl_abort.orphans == set()
    assert loop_errors == []
    assert not [r for r in caplog.records if r.exc_info is not None]
