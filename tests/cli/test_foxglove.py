"""``fleetctl foxglove-url`` against a real relay's TLS web listener."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from pathlib import Path

import pytest

from fleetctl.cli.main import main
from fleetctl.errors import ExitCode
from fleetctl.server.app import RelayServer
from tests.server.conftest import ALICE_TOKEN, make_server  # noqa: F401
from tests.server.foxglove.conftest import web_config  # noqa: F401
from tests.server.foxglove.fxclient import Viewer, open_viewer


async def test_prints_a_url_foxglove_connects_with(
        make_server: Callable[..., RelayServer], web_config: object,  # noqa: F811
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    token_file = tmp_path / "token"
    token_file.write_text(ALICE_TOKEN + "\n")
    async with make_server(web=web_config) as srv:
        assert srv.config.web is not None
        args = ["foxglove-url", "--server", f"https://127.0.0.1:{srv.web_port}/",
                "--token-file", str(token_file), "--ca-file", str(srv.config.web.tls_cert)]
        assert await asyncio.to_thread(main, [*args, "-o", "json"]) == 0
        answer = json.loads(capsys.readouterr().out)
        assert answer["expires_in_s"] == 60.0
        url: str = answer["url"]
        assert url.startswith(f"wss://127.0.0.1:{srv.web_port}/?ticket=")
        async with open_viewer(srv.web_port, url.split("ticket=", 1)[1]) as ws:
            viewer = Viewer(ws)
            await viewer.until(lambda: viewer.server_info is not None)
        assert await asyncio.to_thread(main, args) == 0
        assert "Open connection" in capsys.readouterr().out
        # Plain http: refused before the token leaves the machine.
        assert main(["foxglove-url", "--server", f"http://127.0.0.1:{srv.port}/",
                     "--token-file", str(token_file)]) == ExitCode.CONFIG
        assert "TLS only" in capsys.readouterr().err
