"""``fleetctl e2e``: end-to-end runs over tc-shaped links, with a report and plots."""

from __future__ import annotations

import importlib.util
import os
import re
import secrets
from pathlib import Path
from typing import NoReturn

import typer

from fleetctl.e2e import cleanup, report, runner
from fleetctl.e2e.interrupt import Interrupted, SignalGuard
from fleetctl.errors import ConflictError, EnvironmentMissing, ExitCode, FleetError

_RUN_ID = re.compile(r"[a-z0-9]{1,8}")


def e2e(
    scenario: list[str] = typer.Option(
        [], "--scenario", "-s", help=f"Scenario to run (repeatable): {', '.join(runner.SCENARIOS)}."
    ),
    duration: float = typer.Option(30.0, "--duration", help="Measured seconds per scenario."),
    out: Path = typer.Option(Path("e2e-report"), "--out", help="Report directory."),
    wireguard: str = typer.Option(
        "auto", "--wireguard",
        help="Robots reach the server over WireGuard, as `fleetctl up` deploys them: auto "
             "(when /dev/net/tun exists), on, off (the routed network)."),
    clean: bool = typer.Option(
        False, "--cleanup",
        help="Remove containers and networks left by e2e runs that died; run nothing else."),
    clean_all: bool = typer.Option(
        False, "--all", help="With --cleanup: also what other hosts or older versions left."),
    mount_source: Path | None = typer.Option(
        None, "--mount-source", hidden=True,
        help="Development: mount this checkout's fleetctl/ over the images' package."),
    run_id: str | None = typer.Option(
        None, "--run-id", hidden=True, help="Id of the run in names and labels (tests)."),
) -> None:
    """Run the e2e scenarios; write JSON, Markdown and PNGs; exit 1 if a criterion fails.

    SIGTERM, SIGINT and SIGHUP stop the run: every container and network it
    made is removed and the exit status is 128 + the signal's number.
    """
    if clean:
        _cleanup(clean_all)
        return
    unknown = [s for s in scenario if s not in runner.SCENARIOS]
    if unknown:
        raise FleetError(f"--scenario: unknown {unknown}; choose from {list(runner.SCENARIOS)}",
                         exit_code=ExitCode.USAGE)
    if duration <= 0:
        raise FleetError("--duration must be positive (seconds)", exit_code=ExitCode.USAGE)
    if wireguard not in ("auto", "on", "off"):
        raise FleetError(f"--wireguard must be auto, on or off, not {wireguard!r}",
                         exit_code=ExitCode.USAGE)
    if run_id is not None and not _RUN_ID.fullmatch(run_id):
        raise FleetError("--run-id: 1 to 8 of a-z, 0-9", exit_code=ExitCode.USAGE)
    # Checked before the run, not when the report is written minutes later.
    if importlib.util.find_spec("matplotlib") is None:
        raise EnvironmentMissing("fleetctl e2e draws the report's plots with matplotlib, which "
                                 "is not installed: pip install 'fleetctl[e2e]'")
    _report_dir(out)  # the last check: it is the first thing that writes
    cfg = runner.RunConfig(scenarios=tuple(scenario) or runner.SCENARIOS, duration_s=duration,
                           work_dir=out / "raw",
                           source_dir=mount_source.resolve() if mount_source else None,
                           wireguard=wireguard, run_id=run_id or secrets.token_hex(3))
    with SignalGuard():
        try:
            env, results = runner.run(cfg, progress=lambda s: typer.echo(f"e2e: {s}", err=True))
            path = report.write(out, env, results)
        except Interrupted as exc:
            _interrupted(exc, str(cfg.run_id))
    typer.echo(report.table(results))
    typer.echo(f"report: {path}")
    if not report.overall_ok(results):
        raise typer.Exit(int(ExitCode.FAILURE))


def _report_dir(out: Path) -> None:
    """Make ``--out`` (and its ``raw/``) now: a path that cannot be the report's directory
    is one line before the run, not a traceback after containers were started."""
    if os.path.lexists(out) and not out.is_dir():
        raise ConflictError(f"--out {out}: exists and is not a directory (give a new or "
                            "existing directory for the report)")
    try:
        (out / "raw").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FleetError(f"--out {out}: cannot make the report directory: "
                         f"{exc.strerror or exc}", exit_code=ExitCode.ENVIRONMENT) from None


def _interrupted(exc: Interrupted, run_id: str) -> NoReturn:
    """Say what the signal stopped and what is left; exit 128 + the signal's number."""
    left = cleanup.find(cleanup.CLEANUP_RUNNER, f"{cleanup.RUN_LABEL}={run_id}")
    if left:
        names = ", ".join(r.name for r in left)
        tail = f"{len(left)} container(s)/network(s) remain ({names}): run `fleetctl e2e --cleanup`"
    else:
        tail = "every container and network of the run was removed"
    typer.echo(f"fleetctl: error: e2e run {run_id} {exc}; no report written; {tail}", err=True)
    raise typer.Exit(exc.shell_status)


def _cleanup(everything: bool) -> None:
    gone, kept = cleanup.leftovers(cleanup.CLEANUP_RUNNER, everything=everything)
    removed = cleanup.remove(cleanup.CLEANUP_RUNNER, gone)
    for r in removed:
        typer.echo(f"removed {r.kind} {r.name} (run {r.run_id or '?'})")
    for r in kept:
        why = "its run is in progress" if r.owner and cleanup.owner_alive(r.owner) else \
            "its owner cannot be checked from here (use --all)"
        typer.echo(f"kept {r.kind} {r.name}: {why}", err=True)
    failed = [r for r in gone if r not in removed]
    if failed:
        raise FleetError("could not remove " + ", ".join(f"{r.kind} {r.name}" for r in failed),
                         exit_code=ExitCode.RUNTIME)
    typer.echo(f"e2e cleanup: removed {len(removed)} container(s)/network(s)")


def register(app: typer.Typer) -> None:
    """Add ``e2e`` to *app*."""
    app.command("e2e")(e2e)
