"""The CLI entry point: exit codes and error rendering."""

from __future__ import annotations

import pytest
import typer

from fleetctl.cli import main as cli_main
from fleetctl.errors import ConfigError, ExitCode


def test_version_exits_zero(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main.main(["--version"]) == 0
    assert "fleetctl 0.1.0" in capsys.readouterr().out


def test_unknown_command_is_a_usage_error() -> None:
    assert cli_main.main(["no-such-command"]) == 2


def test_fleet_error_is_one_line_on_stderr(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def broken_app() -> typer.Typer:
        app = typer.Typer()

        @app.command()
        def boom() -> None:
            raise ConfigError("fleet.yaml: robots[0].ip: 10.9.0.2 is outside 10.8.0.0/24")

        return app

    monkeypatch.setattr(cli_main, "build_app", broken_app)
    assert cli_main.main([]) == ExitCode.CONFIG
    err = capsys.readouterr().err
    expected = "fleetctl: error: fleet.yaml: robots[0].ip: 10.9.0.2 is outside 10.8.0.0/24"
    assert err.strip() == expected
    assert "Traceback" not in err
