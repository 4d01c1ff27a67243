"""``fleetctl client --config FILE``: run the robot client (rclpy node + fleet link)."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import stat
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import typer

from fleetctl.errors import ConfigError, EnvironmentMissing, ExitCode, FleetError

_LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
MAX_DOMAIN_ID = 232  # Fast DDS's port arithmetic (ROS 2 docs: 0-232 on Linux)


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
    _warn_if_others_may_read(loaded.token_file)
    _check_domain_id()
    _check_rmw_implementation()  # before rclpy's import, where rcl exits 102
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
    logging.getLogger("fleetctl.client").info("%s", stop_line(stats))
    if print_stats:
        typer.echo(json.dumps(stats, default=str))


def _warn_if_others_may_read(token_file: Path | None) -> None:
    """A WARNING when users other than its owner may read the robot's token file (a shell
    redirect under the usual umask makes it 0644); not refused, as ``--token-file``."""
    if token_file is None:
        return
    with contextlib.suppress(OSError):  # it was just read: a race at most
        mode = token_file.stat().st_mode
        if mode & (stat.S_IRGRP | stat.S_IROTH):
            logging.getLogger("fleetctl.client").warning(
                "token_file %s: other users may read it (mode %04o): chmod 600 it (the "
                "client's user must still read it)", token_file, stat.S_IMODE(mode))


def _check_domain_id() -> None:
    """``ROS_DOMAIN_ID`` as rcl and Fast DDS take it: 300 made the client exit 1 with only
    Fast DDS's "port number is too high" lines, ``abc`` with an rclpy traceback."""
    raw = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not raw:
        return  # unset or empty: domain 0
    value = int(raw) if raw.isdigit() else -1
    if not 0 <= value <= MAX_DOMAIN_ID:
        raise ConfigError(f"ROS_DOMAIN_ID={raw!r} (environment): must be an integer from 0 to "
                          f"{MAX_DOMAIN_ID}, the robot's ROS 2 domain (fleetctl.env, "
                          "robots[].ros_domain_id in fleet.yaml)")


# Where an ament prefix registers each RMW implementation it installs (ament index
# resource type "rmw_typesupport"; rmw_implementation_cmake's
# get_available_rmw_implementations lists them, less rmw_implementation itself).
RMW_RESOURCE_DIR = Path("share", "ament_index", "resource_index", "rmw_typesupport")
_NOT_AN_RMW = "rmw_implementation"  # the dispatcher that loads the chosen one
_RMW_NAME = re.compile(r"rmw_[a-z0-9_]+")


def installed_rmw_implementations(environ: Mapping[str, str] = os.environ,
                                  python_prefix: str = sys.prefix) -> list[str]:
    """The RMW implementations installed for this process, sorted: the ament index's
    ``rmw_typesupport`` resources under every prefix of ``AMENT_PREFIX_PATH`` (apt's ROS
    once its setup file is sourced) and under *python_prefix* (where the PyPI wheels of
    the ``ros`` extra install theirs, with no ``AMENT_PREFIX_PATH``). Reads only
    directory listings: importing rclpy to ask would run rcl's check, which exits."""
    prefixes = [p for p in environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    names: set[str] = set()
    for prefix in (*prefixes, python_prefix):
        with contextlib.suppress(OSError):  # a prefix without RMWs, or not there
            names.update(f.name for f in (Path(prefix) / RMW_RESOURCE_DIR).iterdir()
                         if not f.name.startswith("."))
    names.discard(_NOT_AN_RMW)
    return sorted(names)


def _check_rmw_implementation(environ: Mapping[str, str] = os.environ) -> None:
    """``RMW_IMPLEMENTATION`` naming an RMW that is not installed: rcl exited 102 at
    rclpy's import with its own "Expected RMW implementation identifier" line. Unset or
    empty is rcl's default; when no RMW is registered at all, rclpy's import says what is
    missing."""
    value = environ.get("RMW_IMPLEMENTATION", "")
    installed = installed_rmw_implementations(environ)
    if not value or not installed or value in installed:
        return
    distro = environ.get("ROS_DISTRO", "") if environ.get("ROS_DISTRO", "").isalpha() else ""
    package = (f" (apt: ros-{distro or 'jazzy'}-{value.replace('_', '-')})"
               if _RMW_NAME.fullmatch(value) else "")
    raise ConfigError(f"RMW_IMPLEMENTATION={value!r} (environment): not installed here; "
                      f"installed: {', '.join(installed)}. Install it{package} or choose an "
                      "installed one (fleetctl.env; robots[].rmw_implementation in "
                      "fleet.yaml, then `fleetctl export`)")


def stop_line(stats: dict[str, Any]) -> str:
    """One line an operator can read in the robot's journal after a stop. "N sent" counted
    what was handed to the link, also when no server was ever reached: the messages the
    server acknowledged are said beside it."""
    bridge = stats.get("bridge", {})
    topics = stats.get("topics", {})
    acked = sum(int(t.get("acked", 0)) for t in topics.values() if isinstance(t, dict))
    lost = int(bridge.get("lost_before_client") or 0)  # DDS's losses, never in local_in
    lost_note = f", {lost} local messages lost before the client took them" if lost else ""
    # no_drop messages republished here in bursts deeper than their writer's history
    # (fleetctl.client.ros.republish): a slow local node may have missed them.
    at_risk = int(bridge.get("no_drop_at_risk") or 0)
    if at_risk:
        lost_note += (f", {at_risk} no_drop messages republished in bursts past the local "
                      "history (a slow local reader may have missed them)")
    return (f"client stopped: {bridge.get('local_in')} local messages in, "
            f"{bridge.get('sent')} handed to the link, {acked} acknowledged by the server "
            "(status included), "
            f"{bridge.get('rate_limited')} rate limited, {bridge.get('published_local')} "
            f"frames published locally, {stats.get('connects', 0)} connections "
            f"({stats.get('reconnects')} reconnects), {stats.get('no_drop_overflow')} no_drop "
            f"overflow{lost_note}")


def register(app: typer.Typer) -> None:
    """Add ``client`` to *app*."""
    app.command("client")(_client)
