"""Running a fleet's compose deployment: up, down, status, logs (see :mod:`.compose`).

Every command is an argument list given to the ``docker`` CLI through a
:class:`~fleetctl.deploy.dockercli.Runner`; whichever Compose is installed (the v2 plugin or
Debian's ``docker-compose`` v1) runs the file.
"""

from __future__ import annotations

import ipaddress
import json
import os
import shlex
import shutil
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from fleetctl.deploy import hostports, relocation, tls
from fleetctl.deploy.compose import (
    COMPOSE_DIR,
    COMPOSE_FILE,
    DEFAULT_BIND,
    PROJECT_NAME,
    STATE_FILE,
    WG_INTERFACE,
    ComposePlan,
    Options,
    check_wireguard_choice,
    container_server_config,
    page_host,
    plan_for,
    project_name,
    read_robots,
    render,
    robot_service,
    saved_options,
    write_files,
)
from fleetctl.deploy.dockercli import (
    CONFIG_FILES_LABEL,
    Runner,
    check,
    fleet_filters,
    image_exists,
    subprocess_runner,
)
from fleetctl.deploy.fleet import require_fleet_dir
from fleetctl.deploy.images import image_tag
from fleetctl.deploy.replaynames import replayed_robot
from fleetctl.deploy.replicas import check_count
from fleetctl.deploy.statusrecordings import RecordingSummary, exec_error, server_recordings
from fleetctl.deploy.tls import CERT_RELPATH
from fleetctl.errors import ConfigError, ConflictError, EnvironmentMissing, FleetError
from fleetctl.server.config import load_server_config
from fleetctl.smallfile import MAX_CONFIG_BYTES, read_small_text
from fleetctl.waiting import wait_until
from fleetctl.wire.control import known_battery
from fleetctl.yamlfile import safe_load

Progress = Callable[[str], None]
# How long `up` waits for every container to run and be healthy: the server's health check
# passes within ~10 s here; replicas wait for their NATS cluster first.
STARTUP_TIMEOUT_S = 120.0


@dataclass(frozen=True)
class UpResult:
    """What ``up`` did."""

    compose_file: Path
    wireguard_note: str
    url: str
    robots: tuple[str, ...]
    simulated: bool
    replicas: int = 1
    robot_urls: tuple[str, ...] = ()  # with replicas: every replica, for robots' server_url
    page_urls: tuple[str, ...] = ()
    recording_topics: tuple[str, ...] = ()  # fleet.yaml's recording: what the server records
    recordings_command: str = ""  # how to list them (every replica, the CA when self-signed)
    # Non-empty when the certificate does not cover the URL's host: a browser would warn.
    certificate_note: str = ""


def compose_command(runner: Runner = subprocess_runner) -> list[str]:
    """The Compose command here: ``docker compose`` (v2 plugin) or ``docker-compose`` (v1).

    Raises:
        EnvironmentMissing: neither is installed.
    """
    if runner(["docker", "compose", "version"], None, True).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    raise EnvironmentMissing(
        "neither `docker compose` (v2) nor `docker-compose` (v1) is installed "
        "(Debian: apt-get install docker-compose)"
    )


def compose_argv(fleet_dir: Path, project: str, *args: str,
                 runner: Runner = subprocess_runner) -> list[str]:
    """A compose command on the fleet's generated file."""
    path = fleet_dir.resolve() / ".compose" / "docker-compose.yml"
    return [*compose_command(runner), "-p", project, "-f", str(path), *args]


def container_id(fleet_dir: Path, project: str, service: str,
                 runner: Runner = subprocess_runner) -> str | None:
    """The running container of *service* of THIS fleet's deployment, or ``None``.

    Compose labels each container with the file it came from; a container of the same
    project name started from another fleet directory is not ours and is never touched.
    """
    compose_file = fleet_dir.resolve() / ".compose" / "docker-compose.yml"
    res = runner(["docker", "ps", "-q", *fleet_filters(project, compose_file),
                  "--filter", f"label=com.docker.compose.service={service}"], None, True)
    ids = res.stdout.split() if res.returncode == 0 else []
    return ids[0] if ids else None


def _check_not_changed(fleet_dir: Path, wanted: Options, runner: Runner) -> None:
    """Refuse to switch a running deployment's mode underneath it (a stale compose file)."""
    running = saved_options(fleet_dir)
    if running is None or container_id(fleet_dir, running.project, "server", runner) is None:
        return
    for name in ("project", "wireguard", "sim", "bind", "https_port", "replicas"):
        old, new = getattr(running, name), getattr(wanted, name)
        if old != new:
            raise ConflictError(
                f"{fleet_dir / COMPOSE_DIR / STATE_FILE}: the fleet runs "
                f"{_as_option(name, old)}, not {_as_option(name, new)}; give `up` the same "
                "options, or run `fleetctl down` first (data is kept)")


def _as_option(name: str, value: object) -> str:
    """``up``'s option *name* set to *value* as the operator typed it: ``with --sim``,
    ``without --sim``, ``with --https-port 8443`` (not ``sim=False``)."""
    flag = "--" + name.replace("_", "-")
    if value is False or value is None:
        return f"without {flag}"
    return f"with {flag}" if value is True else f"with {flag} {value}"


def _require_project_not_elsewhere(plan: ComposePlan, runner: Runner) -> None:
    """Refuse a project whose containers another fleet directory's compose file made.

    Compose would recreate that fleet's containers from this file and remove its
    simulated robots as orphans; two directories never drive one project. A compose file
    that is gone (the directory moved while its deployment ran) is no other fleet's.

    Raises:
        ConflictError: naming the project and the other compose file.
    """
    ours = _made_here_or_moved(plan)
    if others := sorted(f for f in _compose_files_of(plan.project, runner) if not ours(f)):
        raise ConflictError(
            f"compose project {plan.project} has containers made from {others[0]}, another "
            "fleet directory's: two directories never share a project (each `up` would "
            "recreate the other's containers); run `fleetctl down` there first, or give "
            "`up` another --project")


def _made_here_or_moved(plan: ComposePlan) -> Callable[[str], bool]:
    """Whether a container of the plan's project, made from a given compose file, is this
    fleet's: made from its file, or from one that is gone (this directory, moved while its
    deployment ran; `_require_project_not_elsewhere` refused every other fleet's)."""
    ours = str(plan.compose_file.resolve())
    return lambda made_from: made_from == ours or not _is_there(made_from)


def _is_there(compose_file: str) -> bool:
    """Whether a compose file a container was made from is still there (not moved away)."""
    return Path(compose_file).is_file()


def project_for_up(fleet_dir: Path, project: str | None,
                   runner: Runner = subprocess_runner) -> relocation.ProjectChoice:
    """The compose project ``up`` deploys *fleet_dir* as: *project* when given, else the
    one its recorded deployment keeps (moved), or its own (new, copied)
    (:func:`relocation.project_for_up`).

    Raises:
        ConfigError: the state file is unreadable or malformed.
        ConflictError: a copy whose default project is the original's.
    """
    if project is not None:
        return relocation.ProjectChoice(project)
    return relocation.project_for_up(fleet_dir, _files_of(runner))


def _files_of(runner: Runner) -> relocation.ComposeFilesOf:
    return lambda project: _compose_files_of(project, runner)


def _require_images(plan: ComposePlan, runner: Runner) -> None:
    names = ["server", *(["client"] if plan.options.sim and plan.robots else [])]
    for name in names:
        tag = image_tag(name, plan.options.version)
        if not image_exists(runner, tag):
            raise EnvironmentMissing(f"image {tag} not found: run `fleetctl build` first")


def _require_free_subnet(plan: ComposePlan, runner: Runner) -> None:
    """Refuse a plain-mode fleet subnet that overlaps another Docker network.

    Without WireGuard the compose network is the fleet subnet, and Docker refuses one that
    overlaps a network it has ("Pool overlaps with other one on this address space", after
    `up` had written the compose file). With WireGuard Docker picks the network itself.

    Raises:
        ConflictError: naming fleet.yaml's subnet and the other network.
    """
    if plan.wireguard:
        return
    listed = runner(["docker", "network", "ls", "-q"], None, True)
    ids = listed.stdout.split() if listed.returncode == 0 else []
    res = runner(["docker", "network", "inspect", *ids], None, True) if ids else None
    if res is None or res.returncode != 0:
        return  # none, or one removed meanwhile: compose says what it finds
    subnet = ipaddress.ip_network(plan.fleet_subnet)
    for net in json.loads(res.stdout):
        if net.get("Name") == f"{plan.project}_fleet":
            continue  # this fleet's own, from an earlier `up`
        for cfg in (net.get("IPAM") or {}).get("Config") or []:
            try:
                other = ipaddress.ip_network(str(cfg.get("Subnet")), strict=False)
            except ValueError:
                continue
            if other.version == subnet.version and other.overlaps(subnet):
                raise ConflictError(
                    f"{plan.fleet_dir / 'fleet.yaml'}: subnet {subnet} overlaps Docker "
                    f"network {net.get('Name')!r} ({other}): without WireGuard the compose "
                    "network is the fleet subnet, and Docker refuses two that overlap; "
                    "remove that network, or run with WireGuard (--wireguard on, which "
                    "needs /dev/net/tun)")


def up(fleet_dir: Path, options: Options, progress: Progress = print,
       runner: Runner = subprocess_runner,
       port_probe: hostports.PortProbe | None = None,
       robots_only: bool = False) -> UpResult:
    """Render and start (or update) the deployment, detached.

    Services whose definition did not change keep running: ``up`` on a running fleet only
    adds, removes or recreates what changed. With *robots_only* (a live update after
    ``add-robot`` & co.) only the simulated robots are started, recreated or removed; the
    server and replicas are left as they run even if their image was rebuilt since, so an
    ``add-user`` never restarts the relay behind the operator's back; and nothing is
    printed (no *progress*, compose's output captured and quoted only if it fails).

    Raises:
        ConfigError: the fleet directory is incomplete, or its server.yaml is one the
            server would refuse (the message names file and field).
        ConflictError: the fleet already runs with other options, a port it publishes
            is taken on this host, or (without WireGuard) its subnet overlaps a Docker
            network.
        EnvironmentMissing: an image or Compose is missing.
        FleetError: compose failed (its output is shown).
    """
    plan = plan_for(fleet_dir, options)
    # What the server would refuse at its start (server/server.yaml edited by hand) is
    # said now, before anything starts: it was a server restarting every few seconds
    # behind `fleet is up`, its reason only in `fleetctl logs`.
    load_server_config(plan.fleet_dir / "server" / "server.yaml")
    _check_not_changed(plan.fleet_dir, options, runner)
    _require_project_not_elsewhere(plan, runner)
    _require_images(plan, runner)
    _require_free_subnet(plan, runner)
    hostports.require_free(
        hostports.published_ports(render(plan)),
        hostports.held_by_fleet(runner, plan.project, _made_here_or_moved(plan)),
        port_probe or hostports.bind_error)
    # A live update is one line of the command that changed the fleet (its note), so it
    # says nothing here and keeps compose's output unless compose fails (check quotes it).
    if not robots_only:
        progress(f"wireguard: {plan.wireguard_note}")
    path = write_files(plan)
    sims = len(plan.robots) if options.sim else 0
    what = ("server" if options.replicas == 1 else
            f"{options.replicas} relay replicas on 3 NATS nodes")
    if not robots_only:
        progress(f"compose file {path}; {what} + {sims} simulated robot(s)")
    check(runner(compose_argv(plan.fleet_dir, plan.project, *_up_args(plan, robots_only),
                              runner=runner), None, robots_only), "compose up")
    urls: tuple[tuple[str, ...], tuple[str, ...]] = ((), ())
    if options.replicas > 1:
        from fleetctl.deploy import composereplicas

        urls = (tuple(composereplicas.robot_urls(plan)), _page_urls(plan))
    recording = container_server_config(plan).get("recording")
    topics = tuple(str(rule["topic"]) for rule in recording["rules"]) if recording else ()
    return UpResult(path, plan.wireguard_note, plan.url,
                    tuple(r.name for r in plan.robots), options.sim, options.replicas, *urls,
                    recording_topics=topics,
                    recordings_command=recordings_command(plan, urls[1]) if topics else "",
                    certificate_note=certificate_note(plan))


def certificate_note(plan: ComposePlan) -> str:
    """What is wrong with the page's URL for the HTTPS certificate, ``""`` when nothing.

    The URL's host is the endpoint's (or the ``--bind`` address): with the operator's own
    certificate (fleet.yaml ``tls:``) issued for another name, ``up`` printed a URL a
    browser warns about. Which of the certificate's names reaches this host is not known
    here (DNS, a proxy), so the URL stays and the note names what the certificate covers.
    """
    host = page_host(plan.options.bind, plan.endpoint_host)
    names = tls.cert_names(plan.tls_cert)
    if names is None:
        return (f"the HTTPS certificate {plan.tls_cert} names no host (no subjectAltName, "
                f"or unreadable): a browser will warn at https://{host}/")
    if tls.covers(names, host):
        return ""
    return (f"the HTTPS certificate {plan.tls_cert} does not cover {host}, only "
            f"{', '.join(names)}: a browser will warn at this URL; open the page by one of "
            f"those names if it reaches this host, or give fleet.yaml tls: a certificate "
            f"for {host}")


def _page_urls(plan: ComposePlan) -> tuple[str, ...]:
    """Every replica's page with replicas; ``()`` for one server (its page is ``plan.url``)."""
    if plan.options.replicas == 1:
        return ()
    from fleetctl.deploy import composereplicas

    return tuple(composereplicas.page_urls(plan))


def recordings_command(plan: ComposePlan, page_urls: tuple[str, ...]) -> str:
    """The ``fleetctl recordings list`` line that works against this deployment."""
    return f"fleetctl recordings list {recordings_options(plan, page_urls)}"


def recordings_options(plan: ComposePlan, page_urls: tuple[str, ...]) -> str:
    """``fleetctl recordings``' options for this deployment: every replica's HTTPS port
    (each records its own senders' frames) on the host people reach the page by
    (:meth:`ComposePlan.page_url`) and, with the fleet's own self-signed certificate,
    ``--ca-file`` (without it the command fails on the certificate)."""
    servers = " ".join(f"--server {url}" for url in page_urls or (plan.url,))
    self_signed = plan.fleet_dir / CERT_RELPATH
    ca = f" --ca-file {shlex.quote(str(self_signed))}" if plan.tls_cert == self_signed else ""
    return f"{servers} --token-file FILE{ca}"


def deployed_recordings_options(fleet_dir: Path) -> str:
    """:func:`recordings_options` of the deployment ``up`` last started in *fleet_dir*.

    Raises:
        FleetError: there is none, or the fleet directory or its state cannot be read
            (:func:`existing_options`, :func:`plan_for`).
    """
    plan = plan_for(fleet_dir, existing_options(fleet_dir))
    return recordings_options(plan, _page_urls(plan))


def _up_args(plan: ComposePlan, robots_only: bool) -> list[str]:
    args = ["up", "-d", "--remove-orphans"]
    if not robots_only:
        return args
    robots = [robot_service(robot) for robot in plan.robots] if plan.options.sim else []
    if robots:
        # Named services only, without the server they depend on.
        return [*args, "--no-deps", *robots]
    # No robot left: only the orphans (removed robots) go; the server stays as it is.
    return [*args, "--no-deps", "--no-recreate", "server"]


def existing_options(fleet_dir: Path, project: str | None = None,
                     runner: Runner = subprocess_runner) -> Options:
    """The options of the deployment ``up`` started in *fleet_dir* (or, moved, where it
    was before).

    Raises:
        ConfigError: *fleet_dir* does not exist, is not a directory or has no
            ``fleet.yaml`` (nor a deployment), or *project* is not a project name.
        FleetError: nothing was started there; or, without *project*, *fleet_dir* is a
            copy of a fleet directory whose deployment it recorded.
    """
    require_fleet_dir(fleet_dir)
    if project is not None:
        check_project(project)
    recorded = relocation.recorded_deployment(fleet_dir, _files_of(runner))
    if recorded is not None and not recorded.ours and project is None:
        # Its status/logs/down were the original's: `down --delete-data` deleted its data.
        raise FleetError(
            f"{fleet_dir.resolve() / COMPOSE_DIR}: no deployment here: this directory is a "
            f"copy of {recorded.elsewhere}, whose deployment (compose project "
            f"{recorded.options.project}) it recorded; `fleetctl up` starts this copy's own")
    options = None if recorded is None else recorded.options
    if options is None:
        if not os.path.lexists(fleet_dir / "fleet.yaml"):
            # Exit 3 as for every other command pointed at a directory that is no fleet.
            raise ConfigError(f"{fleet_dir / 'fleet.yaml'}: not found: {fleet_dir} is not a "
                              "fleet directory (create one with 'fleetctl init', or set "
                              "--fleet / FLEET_DIR)")
        raise FleetError(f"{fleet_dir.resolve() / '.compose'}: no deployment here; "
                         "run `fleetctl up` first (or set --fleet / FLEET_DIR)")
    return replace(options, project=project) if project else options


def down(fleet_dir: Path, options: Options, *, delete_data: bool = False,
         progress: Progress = print, runner: Runner = subprocess_runner) -> None:
    """Stop and remove the containers and networks; the data volume only if *delete_data*.

    Raises:
        FleetError: compose failed.
    """
    _check_project_is_ours(fleet_dir, options.project, delete_data, runner)
    args = ["down", "--remove-orphans", *(["-v"] if delete_data else [])]
    what = "containers, networks and the server's data" if delete_data else \
        "containers and networks (the server's data volume is kept)"
    progress(f"stopping {options.project}: removing {what}")
    check(runner(compose_argv(fleet_dir, options.project, *args, runner=runner), None, False),
          "compose down")
    if delete_data:
        _delete_other_volumes(options.project, progress, runner)


def _delete_other_volumes(project: str, progress: Progress, runner: Runner) -> None:
    """Delete the volumes of *project* that compose's ``down -v`` left.

    ``down -v`` deletes only the volumes the current compose file names: after ``up``,
    ``down``, ``up --replicas 2`` it names ``relay-i-data`` and ``nats-k-data``, and the
    single server's ``server-data`` (registry, sessions, recordings) stayed, the other
    way round the replicas'. Compose labels every volume it makes with its project, and
    :func:`_check_project_is_ours` has established that the project is this fleet's.

    Raises:
        FleetError: docker could not list or delete them (one in use, say).
    """
    res = runner(["docker", "volume", "ls", "-q", "--filter",
                  f"label=com.docker.compose.project={project}"], None, True)
    names = check(res, "docker volume ls").stdout.split()
    if names:
        progress(f"removing {project}'s volumes of an earlier deployment: {', '.join(names)}")
        check(runner(["docker", "volume", "rm", *names], None, True), "docker volume rm")


def _check_project_is_ours(fleet_dir: Path, project: str, delete_data: bool,
                           runner: Runner) -> None:
    """Refuse a ``--project`` that is not this fleet's deployment.

    ``compose -p P -f OURS down`` stops every container of project P, whichever file
    made it, and with ``-v`` deletes P's volumes: another fleet's data. P is this
    fleet's when ``up`` recorded it here (or where the directory was moved from), when
    it is the directory's default name (made from its path), or when its containers came
    from this fleet's compose file; never when this directory is a copy and P the
    original's (:mod:`.relocation`), nor when a compose file of another fleet directory,
    still there, made P's containers.

    Raises:
        ConflictError: P's containers came from another compose file; or, with
            *delete_data*, nothing shows P is this fleet's.
    """
    recorded = relocation.recorded_deployment(fleet_dir, _files_of(runner))
    claimed = {project_name(fleet_dir)}
    if recorded is not None:
        # A copy's recorded project is the original's, even under this path's default.
        claimed = (claimed | {recorded.options.project} if recorded.ours
                   else claimed - {recorded.options.project})
    ours = str(fleet_dir.resolve() / COMPOSE_DIR / COMPOSE_FILE)
    made_from = _compose_files_of(project, runner)
    # Containers of a recorded project made from a compose file that is gone: the
    # directory moved while they ran, and `down` here stops them. One another fleet
    # directory still has: that fleet's, even under this fleet's recorded name (a copy).
    others = sorted(f for f in made_from - {ours} if project not in claimed or _is_there(f))
    if others:
        named = f"compose project {project}" if project in claimed else f"--project {project}"
        raise ConflictError(f"{named}: its containers were made from {others[0]}, "
                            f"not from this fleet's {ours}: run `fleetctl down` with --fleet "
                            "set to that fleet's directory")
    if delete_data and not made_from and project not in claimed:
        last = (f" (it was last deployed as {recorded.options.project})"
                if recorded and recorded.ours else "")
        raise ConflictError(f"--project {project}: no container shows it is this fleet's "
                            f"deployment{last}, so its volumes are not deleted: run "
                            "`fleetctl down --delete-data` without --project")


def deployed_services(fleet_dir: Path) -> list[str]:
    """The services of the compose file ``up`` last wrote in *fleet_dir* (none: [])."""
    path = fleet_dir / COMPOSE_DIR / COMPOSE_FILE
    try:
        document = safe_load(read_small_text(path, MAX_CONFIG_BYTES))
    # Not ours any more (edited, replaced, not text): nothing known.
    except (OSError, UnicodeDecodeError, yaml.YAMLError, RecursionError):
        return []
    services = document.get("services") if isinstance(document, dict) else None
    return sorted(map(str, services)) if isinstance(services, dict) else []


def logs(fleet_dir: Path, options: Options, services: Sequence[str], *, follow: bool,
         runner: Runner = subprocess_runner) -> int:
    """Print the logs (following when *follow*); returns compose's exit code.

    Raises:
        ConfigError: a named service is not one of the deployment's.
        FleetError: the fleet has no containers (never started, or `down` removed them
            with their logs); compose printed only "Attaching to" and exited 0.
    """
    known = deployed_services(fleet_dir)
    unknown = [name for name in services if known and name not in known]
    if unknown:
        raise ConfigError(f"logs: no service {', '.join(map(repr, unknown))} in this fleet's "
                          f"deployment; its services: {', '.join(known)}")
    compose_file = fleet_dir.resolve() / COMPOSE_DIR / COMPOSE_FILE
    res = runner(["docker", "ps", "-a", "-q", *fleet_filters(options.project, compose_file)],
                 None, True)
    if res.returncode == 0 and not res.stdout.strip():
        raise FleetError(f"logs: {options.project} has no containers: the fleet is not "
                         "running (`fleetctl down` removes the containers and their logs; "
                         "`fleetctl up` starts it)")
    args = ["logs", "--no-color", *(["--follow"] if follow else []), *services]
    return subprocess.run(compose_argv(fleet_dir, options.project, *args), check=False).returncode


# --- status ----------------------------------------------------------------------------


# The state of a service of the compose file that has no container.
MISSING = "missing"


@dataclass(frozen=True)
class ServiceState:
    """One container: its service, run state, health (``none`` without a check), restarts.

    A service of the compose file without a container has state ``missing`` and health
    ``unknown``.
    """

    service: str
    state: str
    health: str
    restarts: int


@dataclass(frozen=True)
class TunnelPeer:
    """One WireGuard peer of the server: who, and seconds since its last handshake."""

    robot: str
    address: str
    handshake_age_s: float | None  # None: never


@dataclass(frozen=True)
class StatusReport:
    """Services, the server's robot list and the tunnel (``None``: could not be read)."""

    services: tuple[ServiceState, ...]
    robots: list[dict[str, Any]] | None
    robots_error: str = ""
    tunnel: tuple[TunnelPeer, ...] | None = None
    tunnel_note: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    recordings: RecordingSummary | None = None
    recordings_note: str = ""
    # The robots of the fleet directory; the server's registry keeps removed ones.
    fleet_robots: frozenset[str] | None = None
    # The compose files other than this directory's that containers of the project were
    # made from (the fleet directory moved or copied while its deployment ran).
    elsewhere: tuple[str, ...] = ()

    def _removed(self, robot: dict[str, Any]) -> bool:
        return self.fleet_robots is not None and robot.get("name") not in self.fleet_robots

    def _replay_of(self, robot: dict[str, Any]) -> str | None:
        # `fleetctl replay` sends a recorded husky1 as husky1_replay: not a removed robot.
        name = robot.get("name")
        if self.fleet_robots is None or not isinstance(name, str):
            return None
        return replayed_robot(name, self.fleet_robots)

    def _robot_note(self, robot: dict[str, Any]) -> str:
        replay_of = self._replay_of(robot)
        if replay_of is not None:
            return f"  (replay of {replay_of})"
        return "  (not in fleet.yaml: removed)" if self._removed(robot) else ""

    def _no_containers(self) -> str:
        if not self.elsewhere:
            return "no containers: the fleet is not running"
        # "Not running" was false: the deployment runs, made from the old path.
        return ("no containers made from this directory's compose file, but its project "
                f"has containers made from {', '.join(self.elsewhere)} (was the fleet "
                "directory moved while it ran? `fleetctl down` here stops them)")

    def never_connected(self) -> list[str]:
        """The fleet's robots the server has never seen (empty when either is unknown)."""
        if self.robots is None or self.fleet_robots is None:
            return []
        seen = {r.get("name") for r in self.robots}
        return sorted(self.fleet_robots - seen)

    @property
    def healthy(self) -> bool:
        """Every service runs and is healthy (or has no check)."""
        return not self.problems()

    def problems(self) -> list[str]:
        """What keeps the fleet from being healthy, one phrase per service."""
        if not self.services:
            return [self._no_containers()]
        return [_problem(s) for s in self.services
                if s.state != "running" or s.health not in ("healthy", "none")]

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict."""
        return {
            "healthy": self.healthy,
            "services": [s.__dict__ for s in self.services],
            "robots": None if self.robots is None else [
                {**_robot_json(r), "in_fleet": not self._removed(r),
                 "replay_of": self._replay_of(r)} for r in self.robots],
            "robots_error": self.robots_error or None,
            "never_connected": self.never_connected(),
            "tunnel": None if self.tunnel is None else [t.__dict__ for t in self.tunnel],
            "tunnel_note": self.tunnel_note or None,
            "recordings": (None if self.recordings is None else
                           {**self.recordings.__dict__, "writing": list(self.recordings.writing)}),
            "recordings_note": self.recordings_note or None,
        }

    def _first_width(self) -> int:
        """Width of the first column of all three tables: 24, or the longest name (robot
        names have up to 63 characters, services ``robot-`` before them), so that every
        later column stays under its header."""
        names = [s.service for s in self.services]
        names += [str(r.get("name", "?")) for r in self.robots or []]
        names += self.never_connected() + [t.robot for t in self.tunnel or ()]
        return max([24, *map(len, names)])

    def _robot_lines(self, w: int) -> list[str]:
        """The ROBOT table, its first column *w* wide (:meth:`_first_width`)."""
        if self.robots is None:
            return [f"robots: unknown ({self.robots_error})"]
        rows = [f"{r.get('name', '?')!s:<{w}} {'yes' if r.get('online') else 'no':<7} "
                f"{_battery(r.get('battery_level')):<8} {_ago(r.get('last_seen_s'))}"
                + self._robot_note(r)
                for r in self.robots]
        # The robots being set up: "(no robots yet)" read as if the fleet had none.
        rows += [f"{name:<{w}} {'no':<7} {'-':<8} never" for name in self.never_connected()]
        empty = "(no robots yet)" if self.fleet_robots is None else "(no robots in fleet.yaml)"
        return [f"{'ROBOT':<{w}} {'ONLINE':<7} {'BATTERY':<8} LAST SEEN", *(rows or [empty])]

    def render_text(self) -> str:
        """Plain-text tables."""
        w = self._first_width()
        lines = [f"{'SERVICE':<{w}} {'STATE':<11} {'HEALTH':<10} RESTARTS"]
        lines += [f"{s.service:<{w}} {s.state:<11} {s.health:<10} {s.restarts}"
                  for s in self.services] or [f"({self._no_containers()})"]
        lines.append("")
        lines += self._robot_lines(w)
        lines.append("")
        if self.tunnel is None:
            lines.append(f"tunnel: {self.tunnel_note}")
        else:
            lines.append(f"{'TUNNEL PEER':<{w}} {'ADDRESS':<16} LAST HANDSHAKE")
            lines += [f"{t.robot:<{w}} {t.address:<16} " + (
                "never" if t.handshake_age_s is None else f"{t.handshake_age_s:.0f} s ago")
                for t in self.tunnel] or ["(no peers)"]
        lines += ["", self.recordings.text() if self.recordings is not None
                  else f"recording: {self.recordings_note or 'unknown'}"]
        return "\n".join(lines)


def _problem(state: ServiceState) -> str:
    """One phrase of what is wrong with a service that does not run healthy."""
    if state.state == MISSING:
        return (f"{state.service} has no container (`fleetctl up` with the options the fleet "
                "runs with makes it again)")
    return (f"{state.service} {state.state}"
            + (f" ({state.health})" if state.health != "none" else "")
            + (f", {state.restarts} restarts" if state.restarts else ""))


def _with_missing(present: list[ServiceState], expected: list[str]) -> list[ServiceState]:
    """*present* and a ``missing`` row for each service of the compose file without one.

    A container gone while the rest run (``up`` interrupted after compose made the server,
    a ``docker rm -f``) was simply not listed, and ``status`` said healthy. With no
    container at all the fleet is not running, which the report says once instead.
    """
    if not present:
        return present
    have = {state.service for state in present}
    return present + [ServiceState(name, MISSING, "unknown", 0)
                      for name in expected if name not in have]


def _robot_json(robot: dict[str, Any]) -> dict[str, Any]:
    """A robot of the server's ``/robots`` with an unknown battery as ``None`` (a server
    older than this fleetctl reports the robot's -1 as is)."""
    if "battery_level" not in robot:
        return robot
    return {**robot, "battery_level": _battery_level(robot["battery_level"])}


def _battery_level(value: object) -> float | None:
    """The battery fraction of a ``/robots`` entry; ``None`` when unknown or not a number."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return known_battery(float(value))


def _battery(value: object) -> str:
    """``80%`` for a fraction 0..1 (a robot that reports 0..100 is shown as is, as the
    page does); ``-`` when unknown."""
    level = _battery_level(value)
    if level is None:
        return "-"
    return f"{round(level * 100 if level <= 1 else level)}%"


def _ago(stamp: object, now: float | None = None) -> str:
    """``12 s ago`` for a wall-clock time in seconds since the epoch; ``-`` when unknown."""
    if not isinstance(stamp, int | float):
        return "-"
    return f"{max(0.0, (now or time.time()) - stamp):.0f} s ago"


def status(fleet_dir: Path, options: Options,
           runner: Runner = subprocess_runner) -> StatusReport:
    """Each container's state, health and restarts; robots as the server reports them;
    the server's WireGuard peers and their last handshakes."""
    services = _with_missing(
        [state for _cid, state in _containers(fleet_dir, options.project, runner)],
        deployed_services(fleet_dir))
    mine = str(fleet_dir.resolve() / COMPOSE_DIR / COMPOSE_FILE)
    elsewhere = () if services else tuple(sorted(
        _compose_files_of(options.project, runner) - {mine}))
    server_id = container_id(fleet_dir, options.project, "server", runner)
    robots, error = _server_robots(server_id, runner)
    tunnel, note = _tunnel(fleet_dir, server_id, runner)
    recordings, recordings_note = server_recordings(
        server_id, runner, fleet_dir.resolve() / COMPOSE_DIR / "server" / "server.yaml")
    return StatusReport(tuple(sorted(services, key=lambda s: s.service)), robots, error,
                        tunnel, note, recordings=recordings, recordings_note=recordings_note,
                        fleet_robots=_fleet_robot_names(fleet_dir), elsewhere=elsewhere)


def _compose_files_of(project: str, runner: Runner) -> set[str]:
    """The compose files the containers of *project* were made from (any fleet's)."""
    res = runner(["docker", "ps", "-a", "--filter", f"label=com.docker.compose.project={project}",
                  "--format", f'{{{{.Label "{CONFIG_FILES_LABEL}"}}}}'], None, True)
    if res.returncode != 0:
        return set()
    return {line.strip() for line in res.stdout.splitlines() if line.strip()}


def _containers(fleet_dir: Path, project: str,
                runner: Runner) -> list[tuple[str, ServiceState]]:
    """Each container of the deployment (its id and state), running or not."""
    # Only the containers this fleet's compose file made: `status --project P` of another
    # fleet's project showed that fleet's containers as this one's.
    compose_file = fleet_dir.resolve() / COMPOSE_DIR / COMPOSE_FILE
    res = runner(["docker", "ps", "-aq", *fleet_filters(project, compose_file)], None, True)
    containers = []
    for cid in check(res, "docker ps").stdout.split():
        info = _inspect(cid, runner)
        if info is None:
            continue
        name = info["Config"]["Labels"].get("com.docker.compose.service", cid[:12])
        health = info["State"].get("Health", {}).get("Status", "none")
        containers.append((cid, ServiceState(name, info["State"]["Status"], health,
                                             int(info.get("RestartCount", 0)))))
    return containers


def wait_started(fleet_dir: Path, options: Options, runner: Runner = subprocess_runner,
                 timeout_s: float = STARTUP_TIMEOUT_S, poll_s: float = 1.0) -> None:
    """Wait until every container of the deployment runs and is healthy (or has no check).

    `up` said `fleet is up` as soon as compose had created the containers: a server that
    then failed at its start (a damaged registry database, a tunnel it could not bring up)
    restarted every few seconds behind that line.

    Raises:
        FleetError: a container exited, restarted since the wait began or is unhealthy
            (at once), or is not healthy within *timeout_s*: naming it, with its last log
            lines.
    """
    restarts = {state.service: state.restarts
                for _cid, state in _containers(fleet_dir, options.project, runner)}
    pending: list[tuple[str, ServiceState]] = []  # not ready at the last look

    def started() -> bool:
        pending[:] = [(cid, state) for cid, state in
                      _containers(fleet_dir, options.project, runner)
                      if state.state != "running" or state.health not in ("healthy", "none")
                      or state.restarts > restarts.get(state.service, 0)]
        for cid, state in pending:
            if (state.state in ("exited", "dead", "restarting") or state.health == "unhealthy"
                    or state.restarts > restarts.get(state.service, 0)):
                raise FleetError(f"{_described(state)}: it did not start; "
                                 f"{_last_lines(cid, runner)}")
        return not pending

    def not_healthy() -> FleetError:
        cid, state = pending[0]
        return FleetError(f"{_described(state)}: not healthy after {timeout_s:.0f} s; "
                          f"{_last_lines(cid, runner)}")

    wait_until(started, timeout_s, poll_s, timeout_error=not_healthy)


def _described(state: ServiceState) -> str:
    return (f"{state.service} {state.state} ({state.health}"
            + (f", {state.restarts} restarts" if state.restarts else "") + ")")


def _last_lines(cid: str, runner: Runner, count: int = 3) -> str:
    """The last *count* lines *cid* logged, and where the rest is, for an error line."""
    res = runner(["docker", "logs", "--tail", str(count), cid], None, True)
    lines = [" ".join(line.split())[:300] for line in (res.stdout + res.stderr).splitlines()
             if line.strip()][-count:]
    return ((f"its last lines: {' | '.join(lines)}; " if res.returncode == 0 and lines else "")
            + "`fleetctl logs` and `fleetctl status` have the rest")


def _fleet_robot_names(fleet_dir: Path) -> frozenset[str] | None:
    """The robots of the fleet directory (those with a ``robots/NAME/client.yaml``), or
    ``None`` when it cannot be read."""
    try:
        return frozenset(p.parent.name for p in (fleet_dir / "robots").glob("*/client.yaml"))
    except OSError:
        return None


def _inspect(cid: str, runner: Runner) -> dict[str, Any] | None:
    res = runner(["docker", "inspect", cid], None, True)
    if res.returncode != 0:
        return None
    data: list[dict[str, Any]] = json.loads(res.stdout)
    return data[0] if data else None


# FLEETCTL_HEALTH is one URL, or (the replicas' gateway) one per replica: the first that
# answers gives the list (the registry is shared between replicas).
_ROBOTS_SNIPPET = (
    "import os,sys,urllib.request\n"
    "for h in os.environ['FLEETCTL_HEALTH'].split():\n"
    "    try:\n"
    "        print(urllib.request.urlopen(h.rsplit('/',1)[0]+'/robots',timeout=3).read()"
    ".decode()); break\n"
    "    except OSError as e: err=e\n"
    "else: sys.exit(f'no replica answered: {err}')\n"
)


def _server_robots(server_id: str | None,
                   runner: Runner) -> tuple[list[dict[str, Any]] | None, str]:
    if server_id is None:
        return None, "the server container is not running"
    # Asked from inside the server container: /robots answers loopback without a token.
    res = runner(["docker", "exec", "--user", "fleetctl", server_id, "python3", "-c",
                  _ROBOTS_SNIPPET], None, True)
    if res.returncode != 0:
        return None, exec_error(res.stderr, server_id)
    try:
        data = json.loads(res.stdout)
    except json.JSONDecodeError:
        return None, "server /robots is not JSON"
    robots = data.get("robots", data) if isinstance(data, dict) else data
    if not isinstance(robots, list):
        return None, ""
    # The robots the server's auth map expects and has not seen are listed by the server
    # too (for the page); status says which have never connected from fleet.yaml, the
    # source of truth here (StatusReport.never_connected).
    return [r for r in robots if not (isinstance(r, dict) and r.get("never_connected"))], ""


def _tunnel(fleet_dir: Path, server_id: str | None,
            runner: Runner) -> tuple[tuple[TunnelPeer, ...] | None, str]:
    if server_id is None:
        return None, "unknown (the server container is not running)"
    res = runner(["docker", "exec", server_id, "wg", "show", WG_INTERFACE, "dump"], None, True)
    if res.returncode != 0:
        return None, "off (no WireGuard interface in the server container)"
    names = _peer_names(fleet_dir)
    now = time.time()
    peers = []
    # `wg show dump`: the interface line, then per peer: public-key, preshared-key,
    # endpoint, allowed-ips, latest-handshake (epoch s, 0 = never), rx, tx, keepalive.
    for line in res.stdout.splitlines()[1:]:
        cols = line.split("\t")
        if len(cols) < 5:
            continue
        address = cols[3].split(",")[0].split("/")[0]
        stamp = int(cols[4]) if cols[4].isdigit() else 0
        peers.append(TunnelPeer(names.get(address, "?"), address,
                                None if stamp == 0 else max(0.0, now - stamp)))
    # wg lists peers in its own order: by robot name as the ROBOT table above it, peers
    # of no robot of fleet.yaml last.
    return tuple(sorted(peers, key=_peer_order)), ""


def _peer_order(peer: TunnelPeer) -> tuple[bool, str, str]:
    return peer.robot == "?", peer.robot, peer.address.rjust(15)


def _peer_names(fleet_dir: Path) -> dict[str, str]:
    """Robot address -> name, from the fleet's robot WireGuard configs."""
    try:
        return {r.fleet_ip: r.name for r in read_robots(fleet_dir.resolve())}
    except FleetError:
        return {}


def check_project(project: str) -> None:
    """Refuse a ``--project`` outside Compose's project-name alphabet (Compose would
    quietly change it: ``Bad/Name`` is project ``badname``, maybe another fleet's).

    Raises:
        ConfigError: naming the option.
    """
    if not PROJECT_NAME.fullmatch(project):
        raise ConfigError(f"--project {project!r}: expected 1-63 of a-z 0-9 _ - "
                          "(starting with a letter or digit)")


def default_options(fleet_dir: Path, **chosen: Any) -> Options:
    """Options for ``up`` with the default project name of *fleet_dir*.

    ``--bind`` and ``--project`` reach the compose file and the compose command line, so
    they are checked here: an IP address (not a port mapping), and Compose's project-name
    alphabet.

    Raises:
        ConfigError: a bad ``--bind`` or ``--project``, naming the option.
        FleetError: ``--wireguard`` is not auto, on or off (exit 2).
    """
    project = chosen.pop("project", None) or project_name(fleet_dir)
    check_project(project)
    bind = chosen.get("bind", DEFAULT_BIND)
    try:
        ipaddress.ip_address(bind)
    except ValueError:
        raise ConfigError(f"--bind {bind!r}: expected an IP address of this host, e.g. "
                          "127.0.0.1 or 0.0.0.0") from None
    check_count(chosen.get("replicas", 1))
    check_wireguard_choice(chosen.get("wireguard", "auto"))
    return Options(project=project, **chosen)
