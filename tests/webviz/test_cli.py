"""``fleetctl webviz`` as a process: serves, says where, stops cleanly on SIGTERM."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import urllib.request

from fleetctl.cli.main import main

START_TIMEOUT_S = 30


def test_serves_until_sigterm() -> None:
    cmd = [
        sys.executable,
        "-m",
        "fleetctl.cli.main",
        "webviz",
        "--port",
        "0",
        "--server-url",
        "ws://127.0.0.1:9/",
    ]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        lines = []
        for _ in range(20):  # warnings (e.g. a missing vendored library) may come first
            lines.append(proc.stderr.readline())  # blocks until a line or EOF (exit)
            m = re.search(r"serving (http://\S+)", lines[-1])
            if m or not lines[-1]:
                break
        assert m, "".join(lines)
        with urllib.request.urlopen(m.group(1) + "config.json", timeout=10) as r:
            assert r.read() == b'{"server_url": "ws://127.0.0.1:9/"}'
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=START_TIMEOUT_S) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_bad_server_url_is_a_clear_error(capsys: object) -> None:
    assert main(["webviz", "--server-url", "http://host:8080/"]) == 3
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert "--server-url" in err and "ws://" in err


def test_malformed_server_url_is_a_clear_error(capsys: object) -> None:
    for url in ("ws://[::1/", "ws://host:99999/", "ws://host:port/"):
        assert main(["webviz", "--server-url", url]) == 3
        err = capsys.readouterr().err  # type: ignore[attr-defined]
        assert err.startswith(f"fleetctl: error: --server-url {url!r}: expected ws://")
        assert "Traceback" not in err


def test_port_in_use_is_a_clear_error(capsys: object) -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["webviz", "--port", str(port)]) == 5
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert f"cannot listen on 127.0.0.1:{port}" in err


def test_bad_host_is_a_config_error_naming_the_option(capsys: object) -> None:
    """It was exit 5 ('cannot listen on not a host:8000'), as if the machine lacked
    something, and did not name --host."""
    for host in ("not a host", "", "1.2.3.999", "010.0.0.1", "-x.example", "a..b",
                 "x" * 300, "h\u00e9.example"):
        assert main(["webviz", "--host", host]) == 3
        err = capsys.readouterr().err  # type: ignore[attr-defined]
        assert err.startswith(f"fleetctl: error: --host {host[:80]!r}: not an IP address "
                              "or a host name"), err
        assert len(err.strip().splitlines()) == 1


def test_host_that_does_not_resolve_is_a_config_error(capsys: object,
                                                      monkeypatch: object) -> None:
    import socket

    def no_such_name(*_args: object, **_kwargs: object) -> list[object]:
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(socket, "getaddrinfo", no_such_name)  # type: ignore[attr-defined]
    assert main(["webviz", "--host", "nosuch.invalid"]) == 3
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert err == ("fleetctl: error: --host 'nosuch.invalid': cannot resolve it: "
                   "Name or service not known\n")
