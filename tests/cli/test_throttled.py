"""Every command that presents a token, against a real relay whose failed-login budget
for the caller's address is spent: one line naming the situation and the wait, exit 7
(``ExitCode.RETRY_LATER``), never a traceback, never the token (docs/client.md, "Too many
failed logins")."""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from fleetctl.cli.main import main
from fleetctl.errors import ExitCode
from fleetctl.server import loginbudget
from fleetctl.server.app import RelayServer
from fleetctl.server.config import WebConfig
from tests.cli.test_recordings import write_recording
from tests.server.conftest import ALICE_TOKEN, make_server  # noqa: F401
from tests.server.foxglove.conftest import web_config  # noqa: F401

WRONG = "not-alices-token"


@pytest.fixture(autouse=True)
def budgeted_loopback(monkeypatch: pytest.MonkeyPatch) -> None:
    """The CLI connects from 127.0.0.1, which has no budget (docs/security.md): here it
    has one, of 3 failures, then one a minute (Retry-After 60)."""
    monkeypatch.setattr(loginbudget, "UNLIMITED", frozenset())
    monkeypatch.setattr(loginbudget, "FAILURES_BURST", 3)
    monkeypatch.setattr(loginbudget, "FAILURE_INTERVAL_S", 60.0)


def token_file(tmp_path: Path, token: str) -> str:
    path = tmp_path / f"{token}.token"
    path.write_text(token + "\n")
    path.chmod(0o600)  # else a warning comes first on stderr
    return str(path)


def the_error(capsys: pytest.CaptureFixture[str]) -> str:
    """The one line on stderr; no traceback, no token."""
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("fleetctl: error: "), err
    assert "Traceback" not in err and ALICE_TOKEN not in err and WRONG not in err
    return err.strip()


async def test_a_wrong_token_then_every_command_says_retry_later(
        make_server: Callable[..., RelayServer], web_config: WebConfig,  # noqa: F811
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    wrong, alice = token_file(tmp_path, WRONG), token_file(tmp_path, ALICE_TOKEN)
    async with make_server(web=web_config) as srv:
        relay = f"http://127.0.0.1:{srv.port}/"
        listing = ["recordings", "list", "--server", relay, "--token-file"]
        for _ in range(3):  # a stale token, tried by hand: the budget is spent
            assert await asyncio.to_thread(main, [*listing, wrong]) == ExitCode.CONFIG
            assert ": 401 " in the_error(capsys)

        assert await asyncio.to_thread(main, [*listing, alice]) == ExitCode.RETRY_LATER
        assert the_error(capsys) == (
            f"fleetctl: error: {relay}: GET /recordings: refused for now (429): too many "
            "failed logins from this address (the server's failed-login budget per IPv4 "
            "address or IPv6 /64: 20, then one per 2 s): a wrong token here, or on another "
            "client behind the same address or NAT; check --token-file and the other "
            "clients there, then retry in 60 s")

        assert srv.config.web is not None
        web = f"https://127.0.0.1:{srv.web_port}/"
        assert await asyncio.to_thread(main, [
            "foxglove-url", "--server", web, "--token-file", alice, "--ca-file",
            str(srv.config.web.tls_cert)]) == ExitCode.RETRY_LATER
        assert the_error(capsys).startswith(f"fleetctl: error: {web}: GET /foxglove/ticket: "
                                            "refused for now (429): too many failed logins")

        # replay in a process of its own: its link logs to stderr there (Python's last
        # resort handler), and must not print its own "retrying" beside the error.
        write_recording(tmp_path / "rec.mcap", 3, step_ns=1_000_000)
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "fleetctl.cli.main", "replay", str(tmp_path / "rec.mcap"),
            "--server", srv.url, "--token-file", alice, "--rate", "0",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        out, err = await asyncio.wait_for(proc.communicate(), 60)
        assert proc.returncode == ExitCode.RETRY_LATER, err
        assert out == b""
        assert err.decode().startswith(
            f"fleetctl: error: replay: {srv.url}: refused for now (429): too many failed "
            "logins from this address"), err
        assert err.count(b"\n") == 1 and ALICE_TOKEN.encode() not in err, err
        assert srv.core.logins.failures == 3  # none of them cost a hash
