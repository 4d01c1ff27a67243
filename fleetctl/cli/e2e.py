"""``fleetctl e2e``: end-to-end runs over tc-shaped links, with a report and plots."""

from __future__ import annotations

from pathlib import Path

import typer

from fleetctl.e2e import report, runner
from fleetctl.errors import ExitCode, FleetError


def e2e(
    scenario: list[str] = typer.Option(
        [], "--scenario", "-s", help=f"Scenario to run (repeatable): {', '.join(runner.SCENARIOS)}."
    ),
    duration: float = typer.Option(30.0, "--duration", help="Measured seconds per scenario."),
    out: Path = typer.Option(Path("e2e-report"), "--out", help="Report directory."),
    mount_source: Path | None = typer.Option(
        None, "--mount-source", hidden=True,
        help="Development: mount this checkout's fleetctl/ over the images' package."),
) -> None:
    """Run the e2e scenarios; write JSON, Markdown and PNGs; exit 1 if a criterion fails."""
    unknown = [s for s in scenario if s not in runner.SCENARIOS]
    if unknown:
        raise FleetError(f"--scenario: unknown {unknown}; choose from {list(runner.SCENARIOS)}",
                         exit_code=ExitCode.USAGE)
    if duration <= 0:
        raise FleetError("--duration must be positive (seconds)", exit_code=ExitCode.USAGE)
    cfg = runner.RunConfig(scenarios=tuple(scenario) or runner.SCENARIOS, duration_s=duration,
                           work_dir=out / "raw",
                           source_dir=mount_source.resolve() if mount_source else None)
    env, results = runner.run(cfg, progress=lambda s: typer.echo(f"e2e: {s}", err=True))
    path = report.write(out, env, results)
    typer.echo(report.table(results))
    typer.echo(f"report: {path}")
    if not report.overall_ok(results):
        raise typer.Exit(int(ExitCode.FAILURE))


def register(app: typer.Typer) -> None:
    """Add ``e2e`` to *app*."""
    app.command("e2e")(e2e)
