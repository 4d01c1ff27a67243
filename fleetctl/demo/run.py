"""Run the whole demo fleet on this machine: server, simulated robots, their clients, webviz.

Every component is a separate process started by :class:`~fleetctl.demo.supervisor.Supervisor`
(the same ``fleetctl`` commands a real deployment runs). Robot *i*'s sim and client share
``ROS_DOMAIN_ID = base + i``, so robots never see each other's local topics; the client binds
``127.0.1.(i + 2)`` so the server identifies each robot by its source address.
"""

from __future__ import annotations

import json
import math
import signal
import sys
import tempfile
import threading
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

from fleetctl.client.ros.ddsbuffers import CLIENT_FASTDDS_TRANSPORTS
from fleetctl.demo.fleet import CAMERA_HZ, DemoFleet, create_demo_fleet
from fleetctl.demo.supervisor import ProcessSpec, Supervisor
from fleetctl.deploy.fleet import MAX_ROS_DOMAIN_ID
from fleetctl.errors import ExitCode, FleetError
from fleetctl.waiting import wait_until

_HTTP_TIMEOUT_S = 2.0
_WATCH_PERIOD_S = 0.5  # how often a running demo checks that its children are alive


@dataclass(frozen=True)
class DemoOptions:
    """What ``fleetctl demo`` runs.

    Attributes:
        robots: number of simulated robots.
        port: server port; 0 picks a free one.
        webviz_port: webviz HTTP port; 0 picks a free one.
        base_domain_id: ``ROS_DOMAIN_ID`` of the first robot (robot i uses base + i).
        duration_s: stop after this many seconds of running healthy; None runs until
            Ctrl-C / SIGTERM.
        workdir: directory for the fleet's files and logs; None makes a temporary one.
        startup_timeout_s: how long (s) every component gets to become healthy.
        webviz: start ``fleetctl webviz`` when that command exists.
        record: the server records every robot topic (MCAP, ``server/recordings``).
    """

    robots: int = 2
    port: int = 8080
    webviz_port: int = 8000
    base_domain_id: int = 20
    duration_s: float | None = None
    workdir: Path | None = None
    startup_timeout_s: float = 60.0
    webviz: bool = True
    record: bool = False


@dataclass(frozen=True)
class DemoResult:
    """How the demo ended.

    Attributes:
        fleet: what was created.
        online: robot names seen online before stopping.
        exit_codes: each child's exit code, by name.
        stopped_by: ``"duration"``, ``"signal"``.
    """

    fleet: DemoFleet
    online: tuple[str, ...]
    exit_codes: dict[str, int]
    stopped_by: str


def _fleetctl(*args: str) -> list[str]:
    return [sys.executable, "-m", "fleetctl.cli.main", *args]


def _webviz_available() -> bool:
    from fleetctl.cli.main import build_app

    names = {
        cmd.name or (cmd.callback.__name__.replace("_", "-") if cmd.callback else "")
        for cmd in build_app().registered_commands
    }
    return "webviz" in names


def http_json(url: str) -> Any:
    """GET *url* and parse JSON; None when the server is not (yet) answering."""
    try:
        with urllib.request.urlopen(url, timeout=_HTTP_TIMEOUT_S) as response:
            return json.loads(response.read().decode("utf-8"))
    except (urllib.error.URLError, OSError, ValueError):
        return None


def http_ok(url: str) -> bool:
    """True when GET *url* answers 200."""
    try:
        with urllib.request.urlopen(url, timeout=_HTTP_TIMEOUT_S) as response:
            return int(response.status) == 200
    except (urllib.error.URLError, OSError):
        return False


def online_robots(http_url: str) -> set[str]:
    """Names of robots the server reports online (``GET /robots``, from loopback)."""
    data = http_json(f"{http_url}/robots")
    robots = data.get("robots", []) if isinstance(data, dict) else data
    if not isinstance(robots, list):
        return set()
    return {
        str(r["name"]) for r in robots if isinstance(r, dict) and r.get("online") and "name" in r
    }


@contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """Turn SIGINT/SIGTERM into *stop* being set, for the duration of the block."""

    def handler(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


class _Interrupted(Exception):
    """SIGINT/SIGTERM arrived while the demo was starting."""


@dataclass
class _Guard:
    """What every wait checks: a signal arrived, or a child died."""

    supervisor: Supervisor
    stop: threading.Event

    def check(self) -> None:
        """Raise if the demo must stop waiting.

        Raises:
            _Interrupted: a signal asked to stop.
            FleetError: a child exited (the message quotes the end of its log).
        """
        if self.stop.is_set():
            raise _Interrupted
        exited = self.supervisor.exited()
        if exited:
            name, code = next(iter(exited.items()))
            tail = self.supervisor.log_tail(name)
            raise FleetError(f"{name} exited with code {code}; its log ends with:\n{tail}",
                             exit_code=ExitCode.RUNTIME)

    def http_ok(self, url: str) -> bool:
        self.check()
        return http_ok(url)


def _start_components(
    guard: _Guard, fleet: DemoFleet, options: DemoOptions, logs: Path
) -> str | None:
    """Start every process; return the webviz URL, or None when there is no webviz."""
    supervisor = guard.supervisor
    supervisor.start(
        ProcessSpec("server", _fleetctl("server", "--config", str(fleet.server_config)),
                    logs / "server.log")
    )
    wait_until(lambda: guard.http_ok(f"{fleet.http_url}/healthz"), options.startup_timeout_s,
               describe=f"the server at {fleet.http_url}/healthz")
    for i, robot in enumerate(fleet.robots):
        # Discovery stays on loopback: a demo robot must never join the graph of a real
        # robot on the LAN (multicast discovery would put its /goal_pose, /odom there).
        env = {"ROS_DOMAIN_ID": str(robot.ros_domain_id),
               "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
        phase = 2 * math.pi * i / len(fleet.robots)
        supervisor.start(ProcessSpec(
            f"{robot.name}-sim",
            _fleetctl("sim-robot", robot.name, "--phase-rad", f"{phase:.4f}",
                      "--camera-hz", f"{CAMERA_HZ:g}"),
            logs / f"{robot.name}-sim.log", env))
        # The client's DDS as on a robot (fleetctl.env): UDP with a 4 MiB buffer, which
        # the sim's 921 KB camera images need on a loaded machine (docs/robot.md).
        supervisor.start(ProcessSpec(
            f"{robot.name}-client", _fleetctl("client", "--config", str(robot.client_config)),
            logs / f"{robot.name}-client.log",
            {**env, "FASTDDS_BUILTIN_TRANSPORTS": CLIENT_FASTDDS_TRANSPORTS}))
    if not (options.webviz and _webviz_available()):
        return None
    supervisor.start(ProcessSpec(
        "webviz",
        _fleetctl("webviz", "--port", str(options.webviz_port), "--server-url", fleet.ws_url),
        logs / "webviz.log"))
    url = f"http://127.0.0.1:{options.webviz_port}/"
    wait_until(lambda: guard.http_ok(url), options.startup_timeout_s,
               describe=f"the webviz at {url}")
    return url


def _summary(fleet: DemoFleet, webviz_url: str | None, logs: Path,
             record: bool = False) -> list[str]:
    lines = [
        f"fleetctl demo: {len(fleet.robots)} simulated robots, files in {fleet.root}",
        f"  server     {fleet.ws_url}  (health {fleet.http_url}/healthz, "
        f"robots {fleet.http_url}/robots, metrics {fleet.http_url}/metrics)",
    ]
    for robot in fleet.robots:
        lines.append(f"  {robot.name:<10} client from {robot.address}, ROS_DOMAIN_ID="
                     f"{robot.ros_domain_id} (localhost only), topics /{robot.name}/...")
    lines.append(f"  webviz     {webviz_url}  (paste a token below into the page)" if webviz_url
                 else "  webviz     not started")
    lines.append(f"  viewer token   (receive all):         {fleet.viewer_token}")
    lines.append(f"  operator token (also send goal poses): {fleet.operator_token}")
    lines.append(f"  logs       {logs}")
    if record:
        lines.append(f"  recording  {fleet.server_config.parent / 'recordings'}  (fleetctl "
                     f"recordings list --config {fleet.server_config})")
    return lines


def run_demo(options: DemoOptions, out: Callable[[str], None]) -> DemoResult:
    """Run the demo until *duration_s* passes or SIGINT/SIGTERM arrives; stop everything.

    Args:
        options: what to run.
        out: prints one line for the user.

    Raises:
        FleetError: a component failed to start or died (the message quotes its log);
            the options give a robot a ROS domain id past 232 (exit 3).
    """
    last_domain = options.base_domain_id + options.robots - 1
    if last_domain > MAX_ROS_DOMAIN_ID:
        raise FleetError(f"--base-domain-id {options.base_domain_id} with --robots "
                         f"{options.robots}: robot{options.robots} would get ROS_DOMAIN_ID "
                         f"{last_domain}; ROS 2 allows 0-{MAX_ROS_DOMAIN_ID}",
                         exit_code=ExitCode.CONFIG)
    root = options.workdir or Path(tempfile.mkdtemp(prefix="fleetctl-demo-"))
    try:
        fleet = create_demo_fleet(root, options.robots, port=options.port,
                                  base_domain_id=options.base_domain_id,
                                  record=options.record)
    except OSError as exc:  # e.g. --workdir is a regular file, or not writable
        raise FleetError(f"--workdir {root}: cannot write the demo's files: "
                         f"{exc.strerror or exc}", exit_code=ExitCode.CONFIG) from None
    logs = root / "logs"
    guard = _Guard(Supervisor(), threading.Event())
    online: set[str] = set()
    stopped_by = "signal"
    try:
        with _stop_on_signals(guard.stop):
            webviz_url = _start_components(guard, fleet, options, logs)
            wanted = {robot.name for robot in fleet.robots}
            out(f"fleetctl demo: waiting for {', '.join(sorted(wanted))} to come online ...")

            def all_online() -> bool:
                guard.check()
                online.update(online_robots(fleet.http_url) & wanted)
                return online == wanted

            wait_until(all_online, options.startup_timeout_s, poll_s=0.2,
                       describe=f"robots {sorted(wanted)} online in {fleet.http_url}/robots")
            for line in _summary(fleet, webviz_url, logs, options.record):
                out(line)
            out("fleetctl demo: all components healthy; Ctrl-C stops everything")
            stopped_by = _watch(guard, options.duration_s)
    except _Interrupted:
        stopped_by = "signal"
    finally:
        out("fleetctl demo: stopping ...")
        codes = guard.supervisor.stop_all()
    out("fleetctl demo: stopped " + ", ".join(f"{n} ({c})" for n, c in codes.items()))
    return DemoResult(fleet, tuple(sorted(online)), codes, stopped_by)


def _watch(guard: _Guard, duration_s: float | None) -> str:
    """Block until a signal or *duration_s* passes; raise if a child dies meanwhile."""
    remaining = math.inf if duration_s is None else duration_s
    while remaining > 0:
        step = min(_WATCH_PERIOD_S, remaining)
        if guard.stop.wait(step):
            return "signal"
        remaining -= step
        guard.check()
    return "duration"
