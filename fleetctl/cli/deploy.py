"""``fleetctl build``, ``up``, ``down``, ``status``, ``logs``: images and the server host's
compose deployment.

The commands are thin: each calls a library function in :mod:`fleetctl.deploy.images` or
:mod:`fleetctl.deploy.composerun` and prints its result as text or ``--output json``. The
fleet directory comes from ``--fleet DIR``, else ``$FLEET_DIR``, else the current directory,
as for every other fleet command.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from fleetctl.cli.output import (
    PORT,
    AsciiInt,
    OutputFormat,
    changes_text,
    emit,
    fleet_option,
    output_option,
    to_jsonable,
)
from fleetctl.deploy import composerun, images
from fleetctl.deploy import operations as ops
from fleetctl.deploy.compose import DEFAULT_BIND
from fleetctl.deploy.dockercli import require_docker_engine
from fleetctl.deploy.fleet import load_fleet
from fleetctl.deploy.operations import Outcome
from fleetctl.deploy.replicas import MAX_REPLICAS
from fleetctl.errors import ExitCode, FleetError


def _project_option() -> Any:
    return typer.Option(None, "--project", help="Compose project name "
                        "(default: the one `up` used, else fleetctl + the directory's name).")


def require_docker() -> None:
    """The docker command and an engine that answers: every command here needs both, and
    without the engine compose (v1) printed a Python traceback before fleetctl's line."""
    require_docker_engine()


def _progress(line: str) -> None:
    typer.echo(f"fleetctl: {line}", err=True)


def build(
    image: list[str] = typer.Option(
        [], "--image", "-i", help="Image to build (repeatable); default: all."
    ),
    source: Path | None = typer.Option(
        None, "--source", help="Build from this fleetctl checkout (default: the installed "
        "fleetctl, or the checkout it runs from)."),
    base_image: str = typer.Option(
        images.BASE_IMAGE, "--base-image", help="Base image; the default is made locally."
    ),
    mirror: str | None = typer.Option(
        None, "--mirror", help="Debian mirror for debootstrap (default: apt's)."
    ),
    output: OutputFormat = output_option(),
) -> None:
    """Build the server, client, webviz and router images (no registry needed)."""
    cfg = images.BuildConfig(
        source_dir=images.check_source_dir(source) if source else images.find_source_dir(),
        base_image=base_image,
        mirror_url=mirror,
        images=tuple(image) or images.IMAGE_NAMES,
    )
    images.check_build_options(cfg)  # a typo is a usage error, with or without Docker
    require_docker()
    tags = images.build_all(cfg, progress=_progress)
    emit({"images": tags}, output, lambda: "\n".join(tags))


def up(
    fleet: Path = fleet_option(),
    wireguard: str = typer.Option(
        "auto", "--wireguard", help="auto | on | off: run the tunnel (auto: when /dev/net/tun "
        "exists)."),
    sim: bool = typer.Option(
        False, "--sim", help="Also run a simulated robot (ROS 2 sim + real client) for every "
        "robot of the fleet, to try the fleet out on this host."),
    bind: str = typer.Option(
        DEFAULT_BIND, "--bind", help="Host address the HTTPS and WireGuard ports are "
        "published on (127.0.0.1: this host only)."),
    https_port: int | None = typer.Option(
        None, "--https-port", parser=PORT,
        help="Host port of the page + WebSocket (default: the fleet's https_port)."),
    project: str | None = typer.Option(
        None, "--project", help="Compose project name (default: the one `up` used here, "
        "also after the directory was moved; else fleetctl + the directory's name)."),
    replicas: int | None = typer.Option(
        None, "--replicas", parser=AsciiInt(1, MAX_REPLICAS),
        help=f"Relay replicas, 1..{MAX_REPLICAS}, on a 3-node NATS cluster (robots fail over "
        "between them); "
        "1: one server, no NATS. Recorded in fleet.yaml (relay_replicas), which robots' "
        "client.yaml follow; default: fleet.yaml's (1 when not set)."),
    output: OutputFormat = output_option(),
) -> None:
    """Start the fleet on this server host: server, web page and WireGuard (docker compose).

    On a running fleet it applies what changed and leaves the rest running.
    It returns once every service runs and is healthy; a service that fails
    to start is exit 1, naming it with its last log lines.
    """
    require_docker()
    recorded = load_fleet(fleet).relay_replicas
    count = recorded if replicas is None else replicas
    if count != recorded:
        # Whatever would stop the recording below (replica ports that do not fit, a
        # client.yaml edited by hand) stops `up` now, before anything is deployed.
        with ops.fleet_lock(fleet, dry_run=True):
            ops.set_relay_replicas(fleet, count, dry_run=True)
    # Without --project: the project this directory's deployment keeps, moved or not (a
    # copy gets its own); the line says which when the directory moved or was copied.
    chosen = composerun.project_for_up(fleet, project)
    options = composerun.default_options(fleet, project=chosen.project, wireguard=wireguard,
                                         sim=sim, bind=bind, https_port=https_port,
                                         replicas=count)
    if chosen.note:
        _progress(chosen.note)
    result = composerun.up(fleet, options, progress=_progress)
    _progress(f"waiting until every service runs and is healthy (at most "
              f"{composerun.STARTUP_TIMEOUT_S:.0f} s)")
    composerun.wait_started(fleet, options)
    recorded_now: Outcome | None = None
    if count != recorded:
        # Only once the deployment runs (up refuses a change of mode on a running fleet):
        # from here on robots' client.yaml list every replica, and a plain `up` keeps them.
        with ops.fleet_lock(fleet):
            recorded_now = ops.set_relay_replicas(fleet, count)

    def text() -> str:
        robots = ", ".join(result.robots) or "none yet"
        lines = [f"fleet is up: open {result.url} and sign in with a user token "
                 "(`fleetctl add-user`)"]
        if result.certificate_note:
            lines += [f"warning: {result.certificate_note}"]
        lines += [f"wireguard: {result.wireguard_note}",
                  f"robots: {robots}{' (simulated)' if result.simulated else ''}"]
        if result.replicas > 1:
            lines += [f"replicas: {result.replicas} (pages: {' '.join(result.page_urls)})"]
        if result.recording_topics:
            lines += [f"recording: {' '.join(result.recording_topics)} into the server's "
                      f"data volume ({result.recordings_command})"]
        if recorded_now is not None:
            lists = (f"every replica: server_url: [{', '.join(result.robot_urls)}]"
                     if count > 1 else "the one server")
            lines += [f"relay_replicas: {count} recorded in fleet.yaml; robots' client.yaml "
                      f"now list {lists}",
                      changes_text(recorded_now.changes, fleet, False),
                      "robots on other hosts follow it once they run a new "
                      "`fleetctl export NAME` bundle"]
        lines += [f"compose file: {result.compose_file}", "next: fleetctl status"]
        return "\n".join(lines)

    emit({**to_jsonable(result), "relay_replicas_recorded": recorded_now is not None},
         output, text)


def down(
    fleet: Path = fleet_option(),
    delete_data: bool = typer.Option(
        False, "--delete-data", help="Also delete the fleet's data volumes: robot registry, "
        "sessions and the server's MCAP recordings (every replica's, and NATS's). Without it, "
        "data is kept for the next `up`."),
    project: str | None = _project_option(),
) -> None:
    """Stop the fleet: remove its containers and networks, keep its data."""
    require_docker()
    options = composerun.existing_options(fleet, project)
    composerun.down(fleet, options, delete_data=delete_data, progress=_progress)


def status(
    fleet: Path = fleet_option(),
    project: str | None = _project_option(),
    output: OutputFormat = output_option(),
) -> None:
    """Show each container (state, health, restarts), each robot and each tunnel peer.

    Exits 1 after the report when a service is not running and healthy, so
    that a script or a monitoring check can act on it.
    """
    require_docker()
    report = composerun.status(fleet, composerun.existing_options(fleet, project))
    emit(report.to_json(), output, report.render_text)
    if not report.healthy:
        raise FleetError("the fleet is not healthy: " + "; ".join(report.problems()),
                         exit_code=ExitCode.FAILURE)


def logs(
    service: list[str] = typer.Argument(None, help="Services (default: all), e.g. server."),
    fleet: Path = fleet_option(),
    follow: bool = typer.Option(False, "--follow", help="Keep printing new lines."),
    project: str | None = _project_option(),
) -> None:
    """Show (or follow) the logs of the fleet's services."""
    require_docker()
    code = composerun.logs(fleet, composerun.existing_options(fleet, project),
                           list(service or []), follow=follow)
    if code != 0:
        raise FleetError(f"compose logs exited with {code}")


def register(app: typer.Typer) -> None:
    """Add ``build``, ``up``, ``down``, ``status`` and ``logs`` to *app*."""
    app.command("build")(build)
    app.command("up")(up)
    app.command("down")(down)
    app.command("status")(status)
    app.command("logs")(logs)
