"""RobotLink meets the relay's failed-login budget (docs/client.md, "Too many failed
logins"): the server is reachable, so the link says why it is refused, waits what the
server asked, and connects once the budget refills. Through a real relay; the budgeted
address is 127.0.0.5 (only 127.0.0.1 and ::1 have no budget)."""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from websockets.asyncio.server import ServerConnection, serve

from fleetctl.client.linktuning import LinkTuning
from fleetctl.client.loginthrottle import EXPLANATION
from fleetctl.client.transport import RobotLink
from fleetctl.server import loginbudget
from fleetctl.server.app import RelayServer
from tests.client.conftest import ROBOT_TOKEN, make_server, robot_config, running, wait_until
from tests.server.conftest import client
from tests.server.test_app import closed_code

SOURCE = "127.0.0.5"  # the robot's address, and a stranger's behind the same NAT
FAST = LinkTuning(keepalive_interval_s=0.1, link_timeout_s=0.6, open_timeout_s=1.0)
# The robot's own backoff (10-20 ms) is far below the server's hint (1 s): only the hint
# can make it wait that long.
QUICK_RETRIES = {"reconnect_min_s": 0.01, "reconnect_max_s": 0.02}


@pytest.fixture
async def throttling_server(tmp_path: Path,
                            monkeypatch: pytest.MonkeyPatch) -> AsyncIterator[RelayServer]:
    """A relay whose budget is 3 failures per address, then one a second (the defaults:
    20, one per 2 s), so that Retry-After is 1 s."""
    monkeypatch.setattr(loginbudget, "FAILURES_BURST", 3)
    monkeypatch.setattr(loginbudget, "FAILURE_INTERVAL_S", 1.0)
    async with make_server(tmp_path) as srv:
        yield srv


async def exhaust_budget(srv: RelayServer, source: str = SOURCE) -> None:
    """Another client at *source* tries a wrong token until the budget is spent."""
    for _ in range(3):
        async with client(srv, source=source, token="wrong") as ws:
            assert await closed_code(ws) == 4401


def test_the_budget_the_log_names_is_the_relays() -> None:
    assert (f"{loginbudget.FAILURES_BURST}, then one per "
            f"{loginbudget.FAILURE_INTERVAL_S:g} s") in EXPLANATION


def _errors(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING
            and r.name.startswith("fleetctl.client")]


async def test_a_429_is_explained_once_waited_out_and_then_connected(
        throttling_server: RelayServer, tmp_path: Path,
        caplog: pytest.LogCaptureFixture) -> None:
    srv = throttling_server
    caplog.set_level(logging.DEBUG, "fleetctl.client.link")
    await exhaust_budget(srv)
    cfg = robot_config(srv.url, tmp_path, bind_address=SOURCE, limits=QUICK_RETRIES)
    async with running(RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)) as link:
        await wait_until(lambda: link.stats()["identities"] == ["r1"])
        stats = link.stats()
    # One refusal: the next attempt came after the budget refilled, not 50 of them at
    # the robot's own 10-20 ms backoff; by the link's own clock it waited >= Retry-After.
    assert srv.core.logins.refusals == 1
    assert stats["login_throttled"] == 1
    assert stats["login_throttled_waited_s"] >= 1.0
    assert stats["login_retry_after_s"] is None  # authenticated: the spell is over
    assert stats["connect_failures"] == 1
    errors = _errors(caplog)
    assert len(errors) == 1, errors
    assert errors[0].startswith(f"{srv.url} is reachable but refuses this robot's token "
                                "for now (HTTP 429, retry in 1 s): too many failed logins "
                                "from this address")
    assert "a wrong token here, or on another client behind the same address or NAT" in errors[0]
    assert "(the server's Retry-After)" in errors[0]
    assert "cannot connect" not in caplog.text
    assert ROBOT_TOKEN not in caplog.text
    assert any(r.levelno == logging.INFO and "takes this robot's token again after" in
               r.getMessage() for r in caplog.records)


async def test_a_wrong_token_is_refused_then_throttled_at_the_servers_pace(
        throttling_server: RelayServer, tmp_path: Path,
        caplog: pytest.LogCaptureFixture) -> None:
    srv = throttling_server
    caplog.set_level(logging.INFO, "fleetctl.client.link")
    (tmp_path / "bad.token").write_text("wrong-token\n")
    cfg = robot_config(srv.url, tmp_path, bind_address=SOURCE, token_file="bad.token",
                       limits=QUICK_RETRIES)
    async with running(RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)) as link:
        # 3 failures spend the budget; then one failure a second, a 429 in between.
        await wait_until(lambda: link.stats()["login_throttled"] >= 2)
        stats = link.stats()
    assert srv.core.logins.failures == 4  # 3, then one when the budget had refilled
    assert stats["login_throttled_waited_s"] >= 1.0
    errors = _errors(caplog)  # each explained once: the token, and the throttle
    assert len(errors) == 2, errors
    assert f"{srv.url} closed: 4401 bad token: the server knows no such token" in errors[0]
    assert errors[1].startswith(f"{srv.url} is reachable but refuses this robot's token")
    assert "wrong-token" not in caplog.text


async def test_a_4429_login_throttled_close_is_waited_out(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The relay closes a token *frame* past the budget with 4429 (the link sends its
    token on the upgrade, so only a server that reads it later does this to it)."""
    message = "too many failed logins from this address: retry in 1 s"
    opened: list[float] = []

    async def handler(ws: ServerConnection) -> None:
        opened.append(asyncio.get_running_loop().time())
        if len(opened) == 1:
            await ws.send(json.dumps({"type": "error", "code": "login_throttled",
                                      "message": message}))
            await ws.close(4429, message)
            return
        await ws.send(json.dumps({"type": "welcome", "identities": ["r1"]}))
        await ws.wait_closed()

    caplog.set_level(logging.INFO, "fleetctl.client.link")
    async with serve(handler, "127.0.0.1", 0) as server:
        port = server.sockets[0].getsockname()[1]
        cfg = robot_config(f"ws://127.0.0.1:{port}/", tmp_path, limits=QUICK_RETRIES)
        async with running(RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)) as link:
            await wait_until(lambda: link.stats()["identities"] == ["r1"])
            stats = link.stats()
    assert stats["login_throttled"] == 1 and stats["connects"] == 2
    assert stats["login_throttled_waited_s"] >= 1.0
    assert opened[1] - opened[0] >= 1.0
    errors = _errors(caplog)
    assert len(errors) == 1 and "(close 4429, retry in 1 s)" in errors[0], errors
    assert "(the server's close reason)" in errors[0]
