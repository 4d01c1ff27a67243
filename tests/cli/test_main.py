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


def _commands(command: object, path: str = "fleetctl") -> list[tuple[str, object]]:
    found = [(path, command)]
    for name, sub in (getattr(command, "commands", None) or {}).items():
        found += _commands(sub, f"{path} {name}")
    return found


def test_every_command_summary_is_one_line() -> None:
    # The help's command list shows a docstring's first paragraph with its line breaks,
    # so a summary wrapped in the source shows up wrapped mid-sentence in `fleetctl -h`.
    import typer.main

    root = typer.main.get_command(cli_main.build_app())
    wrapped = [path for path, command in _commands(root)
               if "\n" in (getattr(command, "help", None) or "").strip().split("\n\n")[0]]
    assert wrapped == []


def test_every_top_level_command_is_in_a_help_panel() -> None:
    app = cli_main.build_app()
    unpanelled = [info.name or getattr(info.callback, "__name__", "?")
                  for info in [*app.registered_commands, *app.registered_groups]
                  if not info.rich_help_panel and not info.hidden]
    assert unpanelled == []


def test_help_panels_hold_what_a_user_looks_for_there(capsys: pytest.CaptureFixture[str]) -> None:
    """schema sat in "Set up a fleet" and foxglove-url in "Run one component"."""
    assert cli_main.main(["-h"]) == 0
    panels: dict[str, list[str]] = {}
    title = ""
    for line in capsys.readouterr().out.splitlines():
        if line.startswith("╭─ "):
            title = line.strip("╭─ ").split(" ─")[0]
        elif line.startswith("│ ") and line[2:3].isalpha():
            panels.setdefault(title, []).append(line.split()[1])
    assert list(panels) == ["Set up a fleet", "Run one component", "Deploy",
                            "Use a running fleet", "Develop and test"]
    assert sorted(panels["Use a running fleet"]) == ["foxglove-url", "recordings", "replay"]
    assert sorted(panels["Develop and test"]) == ["e2e", "schema"]
    assert "schema" not in panels["Set up a fleet"]
    assert "foxglove-url" not in panels["Run one component"]


def test_help_lines_that_the_source_breaks_fit_an_80_column_terminal() -> None:
    # The help keeps the source's line breaks; a broken line longer than the terminal is
    # wrapped again, which leaves a one-word line after it. A one-line paragraph is free
    # to be long: the terminal wraps it cleanly.
    import typer.main

    root = typer.main.get_command(cli_main.build_app())
    too_long = []
    for path, command in _commands(root):
        for paragraph in (getattr(command, "help", None) or "").split("\n\n"):
            lines = paragraph.strip("\n").splitlines()
            too_long += [f"{path}: {line}" for line in lines if len(lines) > 1 and len(line) > 77]
    assert too_long == []


def test_no_help_shows_a_value_after_a_flag(capsys: pytest.CaptureFixture[str]) -> None:
    # typer 0.29 printed `<bool>` after every flag (`--sim <bool>`, even `-h <bool>`),
    # which reads as "takes a value": `fleetctl up --sim true` is then a usage error.
    import typer.main

    root = typer.main.get_command(cli_main.build_app())
    valued_flags = []
    for path, _command in _commands(root):
        assert cli_main.main([*path.split()[1:], "-h"]) == 0
        valued_flags += [f"{path}: {line.strip()}" for line in capsys.readouterr().out.splitlines()
                         if "<bool>" in line]
    assert valued_flags == []


def test_ctrl_c_while_the_commands_load_is_exit_130_without_a_traceback(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Loading every command group takes ~2 s on a small robot computer; a Ctrl-C then
    printed a KeyboardInterrupt traceback from the imports."""
    def interrupted() -> typer.Typer:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli_main, "build_app", interrupted)
    assert cli_main.main(["client", "--help"]) == 130
    captured = capsys.readouterr()
    assert captured.out == "" and "Traceback" not in captured.err
