"""``fleetctl build``, ``up``, ``down``, ``status``, ``logs``: images and a compose deployment.

The commands are thin: each calls a library function in :mod:`fleetctl.deploy.images` or
:mod:`fleetctl.deploy.compose` and prints its result as text or ``--output json``.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

from fleetctl.deploy import compose, images
from fleetctl.deploy.dockercli import require_docker


def _progress(line: str) -> None:
    typer.echo(f"fleetctl: {line}", err=True)


def build(
    image: list[str] = typer.Option(
        [], "--image", "-i", help="Image to build (repeatable); default: all."
    ),
    source: Path | None = typer.Option(None, "--source", help="fleetctl source checkout."),
    base_image: str = typer.Option(
        images.BASE_IMAGE, "--base-image", help="Base image; the default is made locally."
    ),
    mirror: str | None = typer.Option(
        None, "--mirror", help="Debian mirror for debootstrap (default: apt's)."
    ),
) -> None:
    """Build the server, client, webviz and router images (no registry needed)."""
    require_docker()
    cfg = images.BuildConfig(
        source_dir=source or images.find_source_dir(),
        base_image=base_image,
        mirror_url=mirror,
        images=tuple(image) or images.IMAGE_NAMES,
    )
    for tag in images.build_all(cfg, progress=_progress):
        typer.echo(tag)


def up(
    fleet_dir: Path = typer.Argument(Path("."), help="Fleet directory (has fleet.yaml)."),
    wireguard: str = typer.Option(
        "auto", "--wireguard", help="auto | on | off: run robots over WireGuard."
    ),
    project: str | None = typer.Option(None, "--project", help="Compose project name."),
) -> None:
    """Render the compose file of the fleet and start it."""
    require_docker()
    result = compose.up(compose.plan_for(fleet_dir, wireguard=wireguard, project=project),
                        progress=_progress)
    typer.echo(f"compose file: {result.compose_file}")
    typer.echo(f"wireguard: {result.wireguard_note}")


def down(
    fleet_dir: Path = typer.Argument(Path("."), help="Fleet directory."),
    project: str | None = typer.Option(None, "--project", help="Compose project name."),
) -> None:
    """Stop and remove the fleet's containers and networks."""
    require_docker()
    compose.down(compose.existing(fleet_dir, project=project), progress=_progress)


def status(
    fleet_dir: Path = typer.Argument(Path("."), help="Fleet directory."),
    project: str | None = typer.Option(None, "--project", help="Compose project name."),
    output: str = typer.Option("text", "--output", "-o", help="text | json"),
) -> None:
    """Show each service's health and each robot's online state."""
    require_docker()
    report = compose.status(compose.existing(fleet_dir, project=project))
    if output == "json":
        typer.echo(json.dumps(report.to_json(), indent=2))
        return
    typer.echo(report.render_text())


def logs(
    fleet_dir: Path = typer.Argument(Path("."), help="Fleet directory."),
    service: list[str] = typer.Argument(None, help="Services (default: all)."),
    follow: bool = typer.Option(False, "--follow", "-f", help="Follow the logs."),
    project: str | None = typer.Option(None, "--project", help="Compose project name."),
) -> None:
    """Show (or follow) the logs of the fleet's services."""
    require_docker()
    code = compose.logs(compose.existing(fleet_dir, project=project), list(service or []),
                        follow=follow)
    if code != 0:
        raise typer.Exit(code)


def register(app: typer.Typer) -> None:
    """Add ``build``, ``up``, ``down``, ``status`` and ``logs`` to *app*."""
    app.command("build")(build)
    app.command("up")(up)
    app.command("down")(down)
    app.command("status")(status)
    app.command("logs")(logs)
