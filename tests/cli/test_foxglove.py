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
from fleetctl.server.config import WebConfig
from tests.server.certs import self_signed
from tests.server.conftest import ALICE_TOKEN, make_server  # noqa: F401
from tests.server.foxglove.conftest import web_config  # noqa: F401
from tests.server.foxglove.fxclient import Viewer, open_viewer


async def test_prints_a_url_foxglove_connects_with(
        make_server: Callable[..., RelayServer], web_config: object,  # noqa: F811
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    token_file = tmp_path / "token"
    token_file.write_text(ALICE_TOKEN + "\n")
    token_file.chmod(0o600)  # else a warning comes first on stderr
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
        # stdout is the URL alone, so URL=$(fleetctl foxglove-url ...) works; it had the
        # how-to on a second line, which then went into the URL.
        printed = capsys.readouterr()
        assert printed.out.startswith(f"wss://127.0.0.1:{srv.web_port}/?ticket=")
        assert printed.out.count("\n") == 1 and " " not in printed.out.strip()
        assert "Open connection" in printed.err
        # Plain http: refused before the token leaves the machine.
        assert main(["foxglove-url", "--server", f"http://127.0.0.1:{srv.port}/",
                     "--token-file", str(token_file)]) == ExitCode.CONFIG
        assert "TLS only" in capsys.readouterr().err


async def test_tls_failures_say_what_is_wrong(
        make_server: Callable[..., RelayServer], web_config: object,  # noqa: F811
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """https:// to the plain relay port, and a self-signed certificate without --ca-file,
    both said "cannot reach it", though the server was reached."""
    token_file = tmp_path / "token"
    token_file.write_text(ALICE_TOKEN + "\n")
    token_file.chmod(0o600)  # else a warning comes first on stderr
    async with make_server(web=web_config) as srv:
        for port, expected in (
                (srv.port, "no TLS server answered there (a plain ws:// or http:// port? use "
                           "the TLS port, e.g. the web listener): "),
                (srv.web_port, "its certificate is not trusted (self-signed certificate): give "
                               "the CA that signed it with --ca-file")):
            url = f"https://127.0.0.1:{port}/"
            args = ["foxglove-url", "--server", url, "--token-file", str(token_file)]
            assert await asyncio.to_thread(main, args) == ExitCode.FAILURE
            err = capsys.readouterr().err
            assert err.startswith(f"fleetctl: error: --server {url}: {expected}"), err
            assert err.count("\n") == 1


async def test_an_untrusted_certificate_names_ca_file(
        make_server: Callable[..., RelayServer], web_config: object,  # noqa: F811
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Against a fleet's self-signed certificate without --ca-file the message was
    '[SSL: CERTIFICATE_VERIFY_FAILED] certificate verify failed: ... (_ssl.c:1006)'."""
    token_file = tmp_path / "token"
    token_file.write_text(ALICE_TOKEN + "\n")
    token_file.chmod(0o600)  # else a warning comes first on stderr
    async with make_server(web=web_config) as srv:
        for args in (["foxglove-url"], ["recordings", "list"]):
            assert await asyncio.to_thread(main, [
                *args, "--server", f"https://127.0.0.1:{srv.web_port}/",
                "--token-file", str(token_file)]) == ExitCode.FAILURE
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and "its certificate is not trusted" in err
            assert "--ca-file" in err and "server/tls/cert.pem" in err


async def test_a_certificate_for_another_host_says_so_not_ca_file(
        make_server: Callable[..., RelayServer], web_config: WebConfig,  # noqa: F811
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An operator's certificate (fleet.yaml tls:) asked for by another name, e.g.
    `localhost` on the server host, with its CA given: the hint was to give --ca-file,
    which the user had done."""
    token_file = tmp_path / "token"
    token_file.write_text(ALICE_TOKEN + "\n")
    token_file.chmod(0o600)  # else a warning comes first on stderr
    cert, key = self_signed(tmp_path / "other", host="127.0.0.2")  # and localhost
    async with make_server(web=WebConfig(tls_cert=cert, tls_key=key, listen_host="127.0.0.1",
                                         listen_port=0, vendor_dir=web_config.vendor_dir)) as srv:
        url = f"https://127.0.0.1:{srv.web_port}/"
        for args in (["foxglove-url"], ["recordings", "list"]):
            assert await asyncio.to_thread(main, [
                *args, "--server", url, "--token-file", str(token_file),
                "--ca-file", str(cert)]) == ExitCode.FAILURE
            err = capsys.readouterr().err
            assert err.startswith(
                f"fleetctl: error: --server {url}: its certificate is not for this host "
                "(IP address mismatch, certificate is not valid for '127.0.0.1'.): use a "
                "host name or address it names in the URL"), err
            assert err.count("\n") == 1 and "--ca-file" not in err
