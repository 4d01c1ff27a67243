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
