"""Failed logins through a real relay: past an address's budget its tokens are refused
before hashing (429 at the upgrade, 4429 for a token frame), while robots known by that
address and clients at other addresses go on as before; one sampled log line."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable

import pytest
from websockets.exceptions import InvalidStatus

from fleetctl.server import loginbudget
from fleetctl.server.app import RelayServer
from tests.server.conftest import ALICE_TOKEN, client, next_json
from tests.server.test_app import closed_code, http_get


@pytest.fixture
def small_budget(monkeypatch: pytest.MonkeyPatch) -> None:
    """Three failures per address, then one a minute (the defaults: 20, one per 2 s)."""
    monkeypatch.setattr(loginbudget, "FAILURES_BURST", 3)
    monkeypatch.setattr(loginbudget, "FAILURE_INTERVAL_S", 60.0)


async def refused_status(srv: RelayServer, source: str, token: str | None) -> InvalidStatus:
    with pytest.raises(InvalidStatus) as err:
        async with client(srv, source=source, token=token):
            pass
    return err.value


@pytest.mark.usefixtures("small_budget")
async def test_past_the_budget_tokens_are_refused_unhashed(
        make_server: Callable[..., RelayServer], caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    async with make_server() as srv:
        # A stranger at husky1's address (a robot behind the same NAT) tries tokens.
        for _ in range(3):
            async with client(srv, source="127.0.0.2", token="wrong") as ws:
                assert await closed_code(ws) == 4401
        refused = await refused_status(srv, "127.0.0.2", ALICE_TOKEN)  # a good one too
        assert refused.response.status_code == 429
        assert refused.response.headers["Retry-After"] == "60"
        assert b"too many failed logins" in refused.response.body
        status, _ = await http_get(srv.port, "/robots", {"Authorization": "Bearer x"},
                                   source="127.0.0.2")
        assert status == 429
        assert (await http_get(srv.port, "/healthz", source="127.0.0.2"))[0] == 200

        async with client(srv, source="127.0.0.2") as robot:  # known by its address
            assert (await next_json(robot, "welcome"))["identities"] == ["husky1"]
        async with client(srv, source="127.0.0.1", token=ALICE_TOKEN) as alice:
            assert (await next_json(alice, "welcome"))["identities"] == ["alice"]

        assert srv.metrics.errors["bad_token"] == 3
        assert srv.metrics.errors["login_throttled"] == 2
        status, text = await http_get(srv.port, "/metrics")  # the operator on loopback
        assert status == 200 and "fleetctl_failed_login_addresses 1" in text
        assert "fleetctl_failed_login_evictions_total 0" in text
    lines = [r.getMessage() for r in caplog.records]
    assert len([m for m in lines if "failed login" in m]) == 1  # sampled: not per attempt
    assert not [m for m in lines if "closed 4401" in m or "(429" in m]


@pytest.mark.usefixtures("small_budget")
async def test_a_token_frame_past_the_budget_is_closed_4429(
        make_server: Callable[..., RelayServer]) -> None:
    async with make_server() as srv, client(srv, source="127.0.0.9") as waiting:
        for _ in range(3):  # other connections of the same address fail meanwhile
            async with client(srv, source="127.0.0.9") as ws:
                await ws.send(json.dumps({"token": "wrong"}))
                assert (await next_json(ws, "error"))["code"] == "bad_token"
                assert await closed_code(ws) == 4401
        await waiting.send(json.dumps({"token": ALICE_TOKEN}))  # not even looked at
        error = await next_json(waiting, "error")
        assert error["code"] == "login_throttled" and "retry in" in error["message"]
        assert await closed_code(waiting) == 4429
        # A new connection that could only authenticate by a token frame: refused at once.
        assert (await refused_status(srv, "127.0.0.9", None)).response.status_code == 429
        async with client(srv, source="127.0.0.10") as other:  # the next address
            await other.send(json.dumps({"token": ALICE_TOKEN}))
            assert (await next_json(other, "welcome"))["identities"] == ["alice"]
        assert (srv.core.logins.failures, srv.core.logins.refusals) == (3, 2)
