"""``fleetctl client --config FILE``: run the robot client (rclpy node + fleet link)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import typer

from fleetctl.errors import ConfigError, EnvironmentMissing, ExitCode, FleetError

_LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


def _client(
    config: Path = typer.Option(..., "--config", "-c", help="The robot's client.yaml."),
    log_level: str = typer.Option("INFO", "--log-level", help="DEBUG, INFO, WARNING or ERROR."),
    print_stats: bool = typer.Option(False, "--print-stats",
                                     help="Print the link's final counters as JSON on exit."),
) -> None:
    """Run the robot client: local ROS 2 topics to the fleet server and back."""
    from fleetctl.client.config import load_client_config

    if log_level.upper() not in _LOG_LEVELS:  # logging's ValueError was a traceback
        raise FleetError(f"--log-level: unknown level {log_level!r}; use one of "
                         f"{', '.join(_LOG_LEVELS)}", exit_code=ExitCode.USAGE)
    logging.basicConfig(level=log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    loaded = load_client_config(config)  # before rclpy: a bad file fails fast, named
    try:
        from fleetctl.client.ros.runner import run_client
    except ImportError as exc:
        raise EnvironmentMissing(
            f"rclpy is not installed ({exc}); install the ROS extra: pip install 'fleetctl[ros]'"
        ) from exc
    try:
        stats = run_client(loaded)
    except ConfigError as exc:  # e.g. a message type whose ROS package is not installed
        raise ConfigError(f"{config}: {exc}") from exc
    bridge = stats.get("bridge", {})
    # One line an operator can read in the robot's journal after a stop.
    logging.getLogger("fleetctl.client").info(
        "client stopped: %s local messages in, %s sent, %s rate limited, %s frames published "
        "locally, %s reconnects, %s no_drop overflow",
        bridge.get("local_in"), bridge.get("sent"), bridge.get("rate_limited"),
        bridge.get("published_local"), stats.get("reconnects"), stats.get("no_drop_overflow"))
    if print_stats:
        typer.echo(json.dumps(stats, default=str))


def register(app: typer.Typer) -> None:
    """Add ``client`` to *app*."""
    app.command("client")(_client)
