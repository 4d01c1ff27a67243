"""``fleetctl server``: help, config errors, a real run stopped by SIGTERM."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from fleetctl.cli.main import main


def test_help_documents_the_config(capsys: object) -> None:
    assert main(["server", "--help"]) == 0
    out = capsys.readouterr().out  # type: ignore[attr-defined]
    for key in ("listen_port", "auth_map", "trusted_proxies", "outbound_queue_bytes",
                "max_frame_bytes", "no_drop_topics", "tls_cert", "recording:",
                "max_total_bytes", "/recordings/NAME"):
        assert key in out


def test_bad_config_names_file_and_field(tmp_path: Path, capsys: object) -> None:
    cfg = tmp_path / "server.yaml"
    cfg.write_text("auth_map: auth.yaml\nlisten_port: nope\n")
    assert main(["server", "--config", str(cfg)]) == 3
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert str(cfg) in err and "listen_port" in err and "Traceback" not in err
    cfg.write_text("auth_map: auth.yaml\n")  # the auth map is missing
    assert main(["server", "--config", str(cfg)]) == 3
    assert "auth.yaml" in capsys.readouterr().err  # type: ignore[attr-defined]


def test_an_unknown_log_level_is_a_usage_error(tmp_path: Path, capsys: object) -> None:
    # Exit 2 as the client's (it was 3, the code of a bad config file), before the config
    # is read.
    assert main(["server", "--config", str(tmp_path / "none.yaml"), "--log-level", "LOUD"]) == 2
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert "--log-level: unknown level 'LOUD'; use one of debug, info, warning, error" in err
    assert "Traceback" not in err


def test_runs_serves_health_and_stops_on_sigterm(tmp_path: Path) -> None:
    (tmp_path / "auth.yaml").write_text("version: 1\nidentities: []\n")
    cfg = tmp_path / "server.yaml"
    cfg.write_text("listen_host: 127.0.0.1\nlisten_port: 0\nauth_map: auth.yaml\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "fleetctl.cli.main", "server", "--config", str(cfg)],
        stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert proc.stderr is not None
        deadline = time.monotonic() + 30
        url = None
        while url is None and time.monotonic() < deadline:
            line = proc.stderr.readline()
            if "listening on ws://" in line:
                url = line.rsplit("listening on ", 1)[1].strip()
        assert url is not None
        port = url.rstrip("/").rsplit(":", 1)[1]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=5) as resp:
            assert resp.read() == b"ok\n"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=15) == 0
        assert (tmp_path / "fleet.db").exists()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
