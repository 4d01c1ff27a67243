"""``fleetctl demo`` (the whole fleet on this machine) and ``fleetctl sim-robot`` (one robot).

``sim-robot`` is hidden: it is what ``demo`` runs in each robot's process, and needs rclpy.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import typer

from fleetctl.cli.output import PORT_OR_ANY, AsciiInt
from fleetctl.deploy.fleet import MAX_ROS_DOMAIN_ID
from fleetctl.errors import EnvironmentMissing


def _demo(
    robots: int = typer.Option(2, "--robots", "-n", parser=AsciiInt(1, 100),
                               help="Simulated robots (1..100)."),
    port: int = typer.Option(8080, "--port", parser=PORT_OR_ANY,
                             help="Server port (0: pick a free one)."),
    webviz_port: int = typer.Option(8000, "--webviz-port", parser=PORT_OR_ANY,
                                    help="Webviz port (0: pick a free one)."),
    base_domain_id: int = typer.Option(
        20, "--base-domain-id", parser=AsciiInt(0, MAX_ROS_DOMAIN_ID),
        help=f"ROS_DOMAIN_ID of robot 1 (0..{MAX_ROS_DOMAIN_ID}); robot i uses base+i-1."),
    duration: float | None = typer.Option(None, "--duration", min=0.0,
                                          help="Stop after S seconds (default: until Ctrl-C)."),
    workdir: Path | None = typer.Option(None, "--workdir",
                                        help="Directory for files and logs (default: a temp dir)."),
    startup_timeout: float = typer.Option(60.0, "--startup-timeout", min=1.0,
                                          help="Seconds every component gets to become healthy."),
    no_webviz: bool = typer.Option(False, "--no-webviz", help="Do not start the webviz."),
    record: bool = typer.Option(False, "--record", help="Record every robot topic as MCAP "
                                "(server/recordings in the workdir, at most 1 GiB)."),
) -> None:
    """Run a server, simulated robots with their clients, and the webviz on this machine."""
    from fleetctl.demo.fleet import free_port
    from fleetctl.demo.run import DemoOptions, run_demo

    _require_rclpy()
    options = DemoOptions(
        robots=robots,
        port=port,
        webviz_port=webviz_port or free_port(),
        base_domain_id=base_domain_id,
        duration_s=duration,
        workdir=workdir,
        startup_timeout_s=startup_timeout,
        webviz=not no_webviz,
        record=record,
    )
    run_demo(options, typer.echo)


def _sim_robot(
    name: str = typer.Argument(..., help="Robot name (used in logs and events)."),
    phase_rad: float = typer.Option(0.0, "--phase-rad", help="Start angle on the circle (rad)."),
    camera_hz: float = typer.Option(0.0, "--camera-hz", min=0.0, max=60.0,
                                    help="Rate of the raw camera /camera/image_raw (0: off)."),
) -> None:
    """Run one simulated robot (real rclpy publishers) until Ctrl-C / SIGTERM."""
    _require_rclpy()
    from fleetctl.client.ros.sim import SimConfig, run_sim

    run_sim(SimConfig(name=name, phase_rad=phase_rad, raw_camera_hz=camera_hz))


def _require_rclpy() -> None:
    # find_spec, not import: only fleetctl/client/ros imports rclpy (STYLE.md layout rule).
    if importlib.util.find_spec("rclpy") is None:
        raise EnvironmentMissing(
            "rclpy is not installed; install the ROS extra: pip install 'fleetctl[ros]'"
        )


def register(app: typer.Typer) -> None:
    """Add ``demo`` and the hidden ``sim-robot`` to *app*."""
    app.command("demo")(_demo)
    app.command("sim-robot", hidden=True)(_sim_robot)
