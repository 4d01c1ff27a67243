"""The server host's compose deployment of a fleet directory: plan, render, write files.

``fleetctl up`` turns the fleet directory (docs/design.md section 6) into
``FLEET/.compose/docker-compose.yml`` plus container-side files; running it is
:mod:`fleetctl.deploy.composerun`. What runs:

- ``server``: the relay, the web page and WireGuard in one container. People reach page and
  WebSocket through ONE published HTTPS port (the server's ``web:`` listener, TLS with the
  fleet's certificate); robots reach the plain ``ws://`` listener only inside the tunnel
  (it binds the server's WireGuard address and loopback). The WireGuard UDP port is
  published for real robots.
- ``robot-NAME`` (only with ``--sim``): a simulated robot with its real client, joining over
  WireGuard like a real robot would (``Endpoint = server:PORT``).

Live files are mounted, not copied: ``FLEET/server`` is mounted read-only, so the server
sees ``auth.yaml`` changes (it reloads them) and ``wg syncconf`` reads the current peers.
Secrets the unprivileged server process needs (the TLS key) are handed over by the image
entrypoint (``FLEETCTL_SECRETS``), which copies them to a root-owned-then-chowned 0600 file
before dropping privileges; they are never made world-readable on the host.

Networking has two modes, both keeping the server's IP identity of robots real:

- WireGuard (default when ``/dev/net/tun`` exists): server and robots run ``wireguard-go``
  with the configs ``fleetctl`` generated.
- plain (``--wireguard off``, or no TUN device): the compose network *is* the fleet subnet;
  each simulated robot gets its fleet address, so the auth map still matches. ``up`` says so
  loudly.

The file format is Compose "2.4", which both Debian's ``docker-compose`` v1 and the
``docker compose`` v2 plugin accept (v1 cannot read the newer unversioned format's
``depends_on`` conditions). The compose file is data: dicts dumped as YAML, every command an
argument list, never a shell string.
"""

from __future__ import annotations

import hashlib
import ipaddress
import json
import os
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import yaml

from fleetctl import __version__
from fleetctl.deploy.files import FileWrite, WriteFailed, refuse_linked_directories, write_file
from fleetctl.deploy.fleet import MAX_RELAY_REPLICAS, load_fleet, parse_endpoint
from fleetctl.deploy.images import image_tag
from fleetctl.errors import ConfigError, EnvironmentMissing, ExitCode, FleetError
from fleetctl.smallfile import MAX_PEM_BYTES, MAX_SECRET_BYTES, read_small_text
from fleetctl.yamlfile import read_yaml

COMPOSE_DIR = ".compose"
COMPOSE_FILE = "docker-compose.yml"
STATE_FILE = "state.json"
STATE_FLEET_DIR = "fleet_dir"  # the state's key for the directory `up` ran in
RUN_ETC = "/etc/fleetctl/run"  # the compose dir's server files (server.yaml, cert)
FLEET_ETC = "/etc/fleetctl/fleet"  # FLEET/server, live (auth.yaml, wireguard/wg0.conf)
SECRETS_ETC = "/etc/fleetctl/secrets"  # handed to the server user by the entrypoint
SECRETS_RUN = "/run/fleetctl/secrets"
ROBOT_ETC = "/etc/fleetctl/robot"
SERVER_DATA = "/var/lib/fleetctl"  # a named volume: the database and the recordings
RECORDINGS_DIR = f"{SERVER_DATA}/recordings"
SERVER_WG_CONF = f"{FLEET_ETC}/wireguard/wg0.conf"
WG_INTERFACE = "wg0"  # the entrypoint names the interface after the config file
DEFAULT_BIND = "0.0.0.0"


@dataclass(frozen=True)
class RobotEntry:
    """One robot of the deployment.

    Attributes:
        name: Robot name (directory ``robots/NAME``).
        fleet_ip: Its fleet (WireGuard) address, the server's identity of it.
        robot_dir: ``FLEET/robots/NAME`` (has ``client.yaml``).
    """

    name: str
    fleet_ip: str
    robot_dir: Path


@dataclass(frozen=True)
class Options:
    """What the operator chose for ``up``; kept in ``.compose/state.json`` so that ``down``,
    ``status``, ``logs`` and live changes act on the deployment as it was started.

    Attributes:
        project: Compose project name (container name prefix).
        wireguard: ``auto``, ``on`` or ``off`` as asked.
        sim: Run a simulated robot for every robot of the fleet.
        bind: Host address the HTTPS and WireGuard ports are published on.
        https_port: Host port of the HTTPS listener; ``None``: the fleet's ``https_port``.
        version: fleetctl version (image tag) the deployment was started with.
        replicas: Relay replicas; more than 1 adds a 3-node NATS cluster
            (:mod:`fleetctl.deploy.replicas`).
    """

    project: str
    wireguard: str = "auto"
    sim: bool = False
    bind: str = DEFAULT_BIND
    https_port: int | None = None
    version: str = __version__
    replicas: int = 1


@dataclass(frozen=True)
class ComposePlan:
    """Everything needed to render and run one fleet's compose project.

    Attributes:
        fleet_dir: The fleet directory.
        options: The operator's choices.
        wireguard: Run over WireGuard (else the plain network, see the module doc).
        wireguard_note: Why that mode was chosen, shown to the user.
        robots: The robots, in name order.
        server_port: The plain (in-tunnel) WebSocket/HTTP port.
        https_port: The server's HTTPS port inside the container.
        tls_cert: The certificate on the host.
        tls_key: Its private key on the host.
        wireguard_port: Server WireGuard UDP port.
        fleet_subnet: The fleet subnet (``10.8.0.0/24``).
        server_ip: The server's fleet address.
    """

    fleet_dir: Path
    options: Options
    wireguard: bool
    wireguard_note: str
    robots: tuple[RobotEntry, ...]
    server_port: int
    https_port: int
    tls_cert: Path
    tls_key: Path
    wireguard_port: int = 51820
    fleet_subnet: str = "10.8.0.0/24"
    server_ip: str = "10.8.0.1"
    endpoint_host: str | None = None

    @property
    def project(self) -> str:
        """Compose project name."""
        return self.options.project

    @property
    def published_https_port(self) -> int:
        """The host port people open in the browser."""
        return self.options.https_port or self.https_port

    @property
    def published_bind(self) -> str:
        """The bind address as Compose's port syntax wants it (IPv6 in brackets)."""
        bind = self.options.bind
        return f"[{bind}]" if ":" in bind else bind

    @property
    def url(self) -> str:
        """The page's URL as people open it (see :meth:`page_url`)."""
        return self.page_url(self.published_https_port)

    def page_url(self, port: int) -> str:
        """The page's URL at *port*: on the fleet's endpoint host when the port is
        published on every address (the name robots and browsers reach the server host by,
        and one the self-signed certificate carries), else on the ``--bind`` address (the
        only one it is published on; IPv6 in brackets); ``localhost`` when neither names
        the host."""
        return f"https://{page_host(self.options.bind, self.endpoint_host)}:{port}/"

    @property
    def compose_dir(self) -> Path:
        """``FLEET/.compose``."""
        return self.fleet_dir / COMPOSE_DIR

    @property
    def compose_file(self) -> Path:
        """The generated compose file."""
        return self.compose_dir / COMPOSE_FILE


def page_host(bind: str, endpoint_host: str | None) -> str:
    """The host part of the page's URL for ports published on *bind*.

    Args:
        bind: ``up --bind``: a wildcard (``0.0.0.0``, ``::``) or one address.
        endpoint_host: fleet.yaml's endpoint host (``[v6]`` in brackets); ``None``: not set.
    """
    if bind not in ("0.0.0.0", "::"):
        return f"[{bind}]" if ":" in bind else bind
    return endpoint_host or "localhost"


# --- reading the fleet directory --------------------------------------------------------


def _read_mapping(path: Path, what: str) -> dict[str, Any]:
    data = read_yaml(path, what)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return data


def _wg_value(conf: Path, key: str) -> str | None:
    try:
        text = read_small_text(conf, MAX_SECRET_BYTES)
    except (OSError, UnicodeDecodeError):
        return None
    match = re.search(rf"^\s*{key}\s*=\s*(.+?)\s*$", text, re.M)
    return match.group(1) if match else None


def _robot_ip(robot_dir: Path) -> str:
    conf = robot_dir / "wireguard" / "wg0.conf"
    address = _wg_value(conf, "Address")
    if address is None:
        raise ConfigError(f"{conf}: field Address: missing (run `fleetctl render`?)")
    try:
        return str(ipaddress.ip_interface(address.split(",")[0].strip()).ip)
    except ValueError as exc:
        raise ConfigError(f"{conf}: field Address: {address!r} is not an IP address") from exc


def project_name(fleet_dir: Path) -> str:
    """The default compose project of a fleet directory: ``fleetctl`` + its name + a short
    hash of its path, so two fleets with the same directory name never share containers."""
    resolved = fleet_dir.resolve()
    name = re.sub(r"[^a-z0-9]+", "", resolved.name.lower())[:20] or "fleet"
    digest = hashlib.sha256(str(resolved).encode()).hexdigest()[:6]
    return f"fleetctl{name}{digest}"


TUN_DEVICE = Path("/dev/net/tun")
# Characters a bind mount's source path cannot hold in the compose file (see plan_for).
_COMPOSE_PATH_SPECIAL = ":$"


# Compose's project-name alphabet (it changes other names quietly: Bad/Name -> badname).
PROJECT_NAME = re.compile(r"[a-z0-9][a-z0-9_-]{0,62}")
WIREGUARD_CHOICES = ("auto", "on", "off")


def check_wireguard_choice(requested: str) -> None:
    """Refuse a ``--wireguard`` that is not auto, on or off.

    Raises:
        FleetError: exit 2, a usage error like any bad option value.
    """
    if requested not in WIREGUARD_CHOICES:
        raise FleetError(f"--wireguard must be auto, on or off, not {requested!r}",
                         exit_code=ExitCode.USAGE)


def wireguard_wanted(requested: str, tun: Path = TUN_DEVICE) -> bool:
    """Whether to run WireGuard, from ``--wireguard auto|on|off`` and whether *tun* exists.

    ``fleetctl up`` and ``fleetctl e2e`` decide the same way and word the reason their own.

    Raises:
        FleetError: *requested* is not auto, on or off (exit 2, a usage error).
        EnvironmentMissing: ``on`` without a TUN device.
    """
    check_wireguard_choice(requested)
    if requested == "off":
        return False
    if tun.exists():
        return True
    if requested == "on":
        raise EnvironmentMissing(f"--wireguard on, but {tun} does not exist on this host")
    return False


def wireguard_mode(requested: str, tun: Path = TUN_DEVICE) -> tuple[bool, str]:
    """Decide WireGuard on/off (:func:`wireguard_wanted`) and say why, for ``up``.

    Raises:
        FleetError: bad *requested*, or ``on`` without a TUN device.
    """
    if wireguard_wanted(requested, tun):
        return True, "on: wireguard-go in the server (and simulated robot) containers"
    if requested == "off":
        return False, "off (requested): robots use the plain network with their fleet IPs"
    return False, (
        f"WARNING: WireGuard NOT used: {tun} is missing on this host; robots use the plain "
        "network with their fleet IPs"
    )


def _port(value: Any, path: Path, field: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 < value < 65536:
        raise ConfigError(f"{path}: field {field}: expected a port 1..65535, got {value!r}")
    return int(value)


def _web_section(server_yaml: Path, cfg: dict[str, Any]) -> tuple[int, Path, Path]:
    web = cfg.get("web")
    if not isinstance(web, dict):
        raise ConfigError(f"{server_yaml}: field web: missing (made by a fleetctl without "
                          "HTTPS); run `fleetctl render`")
    port = _port(web.get("listen_port", 8443), server_yaml, "web.listen_port")
    paths = []
    for field in ("tls_cert", "tls_key"):
        value = web.get(field)
        if not isinstance(value, str) or not value:
            raise ConfigError(f"{server_yaml}: field web.{field}: missing")
        path = (server_yaml.parent / value).resolve()
        if not path.is_file():
            raise ConfigError(f"{server_yaml}: field web.{field}: {path} does not exist")
        paths.append(path)
    return port, paths[0], paths[1]


def read_robots(fleet_dir: Path) -> tuple[RobotEntry, ...]:
    """The robots with a client config under ``FLEET/robots``, in name order.

    Raises:
        ConfigError: a robot's WireGuard config has no usable ``Address``.
    """
    robots_dir = fleet_dir / "robots"
    found = []
    for robot_dir in sorted(robots_dir.iterdir()) if robots_dir.is_dir() else []:
        if (robot_dir / "client.yaml").is_file():
            found.append(RobotEntry(robot_dir.name, _robot_ip(robot_dir), robot_dir))
    return tuple(found)


def plan_for(fleet_dir: Path, options: Options | None = None) -> ComposePlan:
    """Read the fleet directory and decide the deployment.

    Raises:
        ConfigError: the fleet directory, a config or a WireGuard config is missing or bad
            (the message names file and field).
        FleetError: a bad ``--wireguard`` choice.
    """
    fleet_dir = fleet_dir.resolve()
    if not (fleet_dir / "fleet.yaml").is_file():
        raise ConfigError(f"{fleet_dir / 'fleet.yaml'}: missing; is this a fleet directory? "
                          "(set --fleet or FLEET_DIR)")
    if bad := sorted(set(_COMPOSE_PATH_SPECIAL) & set(str(fleet_dir))):
        # Its path is a bind mount's source: Compose splits "src:dst:ro" on ':' and
        # expands "$NAME", so such a path would mount the wrong directory or none.
        shown = " and ".join(repr(c) for c in bad)
        raise ConfigError(f"{fleet_dir}: the fleet directory's path has {shown}, which a "
                          "docker compose volume cannot carry; move or rename the directory")
    options = options or Options(project_name(fleet_dir))
    server_yaml = fleet_dir / "server" / "server.yaml"
    server = _read_mapping(server_yaml, "server config")
    port = _port(server.get("listen_port", 8080), server_yaml, "listen_port")
    https_port, cert, key = _web_section(server_yaml, server)
    wg_on, note = wireguard_mode(options.wireguard)
    wg_conf = fleet_dir / "server" / "wireguard" / "wg0.conf"
    wg_port = _wg_value(wg_conf, "ListenPort")
    server_addr = _wg_value(wg_conf, "Address")
    if server_addr is None:
        raise ConfigError(f"{wg_conf}: field Address: missing (run `fleetctl render`?)")
    iface = ipaddress.ip_interface(server_addr)
    return ComposePlan(
        fleet_dir=fleet_dir, options=options, wireguard=wg_on, wireguard_note=note,
        robots=read_robots(fleet_dir), server_port=port, https_port=https_port,
        tls_cert=cert, tls_key=key,
        wireguard_port=int(wg_port) if wg_port and wg_port.isdigit() else 51820,
        server_ip=str(iface.ip), fleet_subnet=str(iface.network),
        endpoint_host=_endpoint_host(fleet_dir),
    )


def _endpoint_host(fleet_dir: Path) -> str | None:
    """fleet.yaml's endpoint host (checked as every command checks fleet.yaml), or
    ``None`` when no endpoint is set."""
    endpoint = load_fleet(fleet_dir).endpoint
    return parse_endpoint(endpoint)[0] if endpoint else None


# --- rendering -------------------------------------------------------------------------


def _static(plan: ComposePlan, ip: str) -> dict[str, Any]:
    # Plain mode: the compose network is the fleet subnet, so robots keep their identity.
    return {"fleet": None if plan.wireguard else {"ipv4_address": ip}}


def _wireguard(conf: str) -> dict[str, Any]:
    # wireguard-go needs NET_ADMIN and the TUN device; the entrypoint starts it as root and
    # drops to the fleetctl user once the tunnel is up.
    return {"cap_add": ["NET_ADMIN"], "devices": ["/dev/net/tun:/dev/net/tun"],
            "environment": {"WG_CONFIG": conf, "WG_REQUIRED": "1"}}


def _merge(svc: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(svc.get(key), dict):
            svc[key] = {**svc[key], **value}
        else:
            svc[key] = value
    return svc


def _server_service(plan: ComposePlan) -> dict[str, Any]:
    bind, https = plan.published_bind, plan.published_https_port
    ports = [f"{bind}:{https}:{plan.https_port}/tcp"]
    if plan.wireguard:
        ports.append(f"{bind}:{plan.wireguard_port}:{plan.wireguard_port}/udp")
    svc: dict[str, Any] = {
        "image": image_tag("server", plan.options.version),
        "command": ["fleetctl", "server", "--config", f"{RUN_ETC}/server.yaml"],
        # root only until the entrypoint has set up WireGuard and handed over the secrets.
        "user": "root",
        "volumes": [
            f"{plan.compose_dir / 'server'}:{RUN_ETC}:ro",
            f"{plan.fleet_dir / 'server'}:{FLEET_ETC}:ro",
            f"{plan.compose_dir / 'secrets'}:{SECRETS_ETC}:ro",
            f"server-data:{SERVER_DATA}",
        ],
        "environment": {
            "FLEETCTL_HEALTH": f"http://127.0.0.1:{plan.server_port}/healthz",
            "FLEETCTL_SECRETS": SECRETS_ETC,
        },
        "ports": ports,
        "restart": "unless-stopped",
        "networks": _static(plan, plan.server_ip),
    }
    return _merge(svc, _wireguard(SERVER_WG_CONF)) if plan.wireguard else svc


# "$$" is Compose's escape of "$": the shell sees "$1" and "$2".
_SIM_SCRIPT = (
    'python3 -c "import sys; from fleetctl.client.ros.sim import SimConfig, run_sim; '
    'run_sim(SimConfig(name=sys.argv[1]))" "$$1" & exec fleetctl client --config "$$2"'
)


def _robot_service(plan: ComposePlan, robot: RobotEntry) -> dict[str, Any]:
    svc: dict[str, Any] = {
        "image": image_tag("client", plan.options.version),
        # The name and path travel as positional parameters, never inside the script.
        "command": ["bash", "-c", _SIM_SCRIPT, "fleetctl-sim", robot.name,
                    f"{ROBOT_ETC}/client.yaml"],
        "user": "root",
        "volumes": [f"{robot.robot_dir}:{ROBOT_ETC}:ro"],
        "environment": {
            # Each robot's ROS graph stays inside its container: everything between robots
            # goes through the server, as on real robots.
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        },
        "depends_on": {"server": {"condition": "service_healthy"}},
        "restart": "unless-stopped",
        "networks": _static(plan, robot.fleet_ip),
    }
    if plan.wireguard:
        svc["volumes"].append(f"{plan.compose_dir / 'robots' / robot.name}:/etc/fleetctl/wg:ro")
        _merge(svc, _wireguard("/etc/fleetctl/wg/wg0.conf"))
    if plan.options.replicas > 1:
        # The robot's config with every replica's URL (client-side failover), over the
        # fleet's one-URL file.
        generated = plan.compose_dir / "robots" / robot.name / "client.yaml"
        svc["volumes"].append(f"{generated}:{ROBOT_ETC}/client.yaml:ro")
        svc["depends_on"] = {"relay-1": {"condition": "service_healthy"}}
    return svc


ROBOT_SERVICE_PREFIX = "robot-"


def robot_service(robot: RobotEntry) -> str:
    """The compose service of *robot*'s simulated robot (``up --sim``)."""
    return f"{ROBOT_SERVICE_PREFIX}{robot.name}"


def render(plan: ComposePlan) -> dict[str, Any]:
    """The compose document of *plan* (pure: no files touched)."""
    volumes: dict[str, Any] = {"server-data": {}}
    if plan.options.replicas > 1:
        # Imported here: composereplicas builds on this module's pieces.
        from fleetctl.deploy import composereplicas

        services = composereplicas.services(plan)
        volumes = {name: {} for name in composereplicas.volumes(plan)}
    else:
        services = {"server": _server_service(plan)}
    if plan.options.sim:
        for robot in plan.robots:
            services[robot_service(robot)] = _robot_service(plan, robot)
    for svc in services.values():
        if "networks" in svc:  # not the replicas, which live in the server's namespace
            svc["networks"] = {k: v for k, v in svc["networks"].items() if v} or ["fleet"]
    network: dict[str, Any] = {"driver": "bridge"}
    if not plan.wireguard:
        subnet = ipaddress.ip_network(plan.fleet_subnet)
        network["ipam"] = {"config": [{
            "subnet": str(subnet),
            # .1 is the server's; give docker's gateway the last address instead.
            "gateway": str(subnet.broadcast_address - 1),
        }]}
    return {
        "version": "2.4",
        "services": services,
        "networks": {"fleet": network},
        "volumes": volumes,
    }


def server_service(plan: ComposePlan) -> dict[str, Any]:
    """The ``server`` service exactly as :func:`render` puts it in the compose document (a
    fresh dict, the caller's to change). ``fleetctl e2e`` starts its server from it
    (:mod:`fleetctl.deploy.dockerrun`), so what e2e measures is what ``up`` deploys."""
    service: dict[str, Any] = render(plan)["services"]["server"]
    return service


# --- files ---------------------------------------------------------------------------


def container_server_config(plan: ComposePlan) -> dict[str, Any]:
    """The fleet's server.yaml with container paths and listeners (pure)."""
    cfg = _read_mapping(plan.fleet_dir / "server" / "server.yaml", "server config")
    # Plain ws:// only inside the tunnel (and loopback, for the health check and status).
    cfg["listen_host"] = [plan.server_ip, "127.0.0.1"] if plan.wireguard else "0.0.0.0"
    cfg["database"] = f"{SERVER_DATA}/fleet.db"
    if isinstance(cfg.get("recording"), dict):
        # On the data volume beside the database: recordings outlive `down` and a new image.
        cfg["recording"] = {**cfg["recording"], "directory": RECORDINGS_DIR}
    auth = Path(str(cfg.get("auth_map") or "auth.yaml"))
    if auth.is_absolute() or ".." in auth.parts:
        raise ConfigError(f"{plan.fleet_dir / 'server/server.yaml'}: field auth_map: must be "
                          "a file inside server/ for a compose deployment")
    cfg["auth_map"] = f"{FLEET_ETC}/{auth.as_posix()}"
    cfg["tls_cert"] = cfg["tls_key"] = None
    cfg["web"] = {**cfg["web"], "listen_host": "0.0.0.0", "tls_cert": f"{RUN_ETC}/tls-cert.pem",
                  "tls_key": f"{SECRETS_RUN}/tls.key"}
    return cfg


def server_config_text(plan: ComposePlan) -> str:
    """``FLEET/.compose/server/server.yaml`` as :func:`write_files` writes it."""
    return yaml.safe_dump(container_server_config(plan), sort_keys=False)


def robot_wireguard(plan: ComposePlan, robot: RobotEntry) -> str:
    """The robot's wg0.conf with ``Endpoint = server:PORT``: inside compose the server is
    reached by its service name, whatever public endpoint fleet.yaml names (or none yet)."""
    text = read_small_text(robot.robot_dir / "wireguard" / "wg0.conf", MAX_SECRET_BYTES)
    endpoint = f"Endpoint = server:{plan.wireguard_port}"
    text, count = re.subn(r"(?m)^\s*Endpoint\s*=.*$", endpoint, text)
    if count == 0:
        text = re.sub(r"(?m)^(\s*PublicKey\s*=.*)$", rf"\g<1>\n{endpoint}", text, count=1)
    return text


def write_files(plan: ComposePlan) -> Path:
    """Write the compose file, state and container-side files under ``FLEET/.compose``."""
    out = plan.compose_dir
    try:
        for sub in (out, out / "secrets"):
            refuse_linked_directories(plan.fleet_dir, sub)  # chmod and the key copy follow one
            sub.mkdir(parents=True, exist_ok=True)
            os.chmod(sub, 0o700)  # copies of private keys live below
        (out / "server").mkdir(exist_ok=True)
    except OSError as exc:
        # A fleet directory on a read-only mount, or owned by another user: one line (it
        # was mkdir's traceback).
        raise WriteFailed.from_os_error(exc) from None
    _write(out / "server" / "server.yaml", server_config_text(plan))
    _write(out / "server" / "tls-cert.pem", read_small_text(plan.tls_cert, MAX_PEM_BYTES))
    _write(out / "secrets" / "tls.key", read_small_text(plan.tls_key, MAX_PEM_BYTES),
           secret=True)
    if plan.wireguard and plan.options.sim:
        for robot in plan.robots:
            _write(out / "robots" / robot.name / "wg0.conf", robot_wireguard(plan, robot),
                   secret=True)
    if plan.options.replicas > 1:
        from fleetctl.deploy import composereplicas  # builds on this module (see render)

        composereplicas.write_files(plan, _write)
    _write(plan.compose_file, "# Generated by `fleetctl up` from the fleet directory; "
           "do not edit.\n" + yaml.safe_dump(render(plan), sort_keys=False))
    # The resolved fleet directory tells a moved directory from a copy (deploy/relocation.py).
    state = {**asdict(plan.options), STATE_FLEET_DIR: str(plan.fleet_dir.resolve())}
    _write(out / STATE_FILE, json.dumps(state, indent=2) + "\n")
    return plan.compose_file


def _write(path: Path, text: str, *, secret: bool = False) -> None:
    # Atomic, mode set at creation, never through a symlink planted in .compose/.
    mode = 0o600 if secret else 0o644
    fleet_dir = next(p.parent for p in path.parents if p.name == COMPOSE_DIR)
    write_file(FileWrite(path, text.encode(), mode, 0o700 if secret else None),
               root=fleet_dir)


@dataclass(frozen=True)
class SavedState:
    """What ``up`` recorded in ``FLEET/.compose/state.json``.

    Attributes:
        options: The options it started the deployment with.
        fleet_dir: The resolved fleet directory it ran in; ``None`` in a state written by
            a fleetctl before 2026-12-06, which did not record it.
    """

    options: Options
    fleet_dir: Path | None


def saved_state(fleet_dir: Path) -> SavedState | None:
    """The state of the deployment ``up`` last started here, or ``None``.

    Raises:
        ConfigError: the state file is unreadable or malformed.
    """
    path = fleet_dir.resolve() / COMPOSE_DIR / STATE_FILE
    if not path.is_file():
        return None
    try:
        data = json.loads(read_small_text(path))
        recorded_dir = data.pop(STATE_FLEET_DIR, None)
        if recorded_dir is not None and not (  # a path the file system takes (no NUL)
                isinstance(recorded_dir, str) and Path(recorded_dir).is_absolute()
                and "\0" not in recorded_dir):
            raise ValueError(f"{STATE_FLEET_DIR}: {recorded_dir!r}")
        options = Options(**data)
        _check_state(options)
        return SavedState(options, None if recorded_dir is None else Path(recorded_dir))
    except (OSError, ValueError, TypeError, AttributeError) as exc:
        raise ConfigError(f"{path}: unreadable deployment state ({exc}); "
                          "remove it and run `fleetctl up` again") from None


def saved_options(fleet_dir: Path) -> Options | None:
    """The options of the deployment ``up`` last started here, or ``None``.

    Raises:
        ConfigError: the state file is unreadable or malformed.
    """
    state = saved_state(fleet_dir)
    return None if state is None else state.options


def _check_state(options: Options) -> None:
    """What ``up`` checked before it saved them: the project and bind address reach the
    compose command line and the image tag; a state file edited or damaged since is not
    passed on (Compose made ``Bad/Name`` project ``badname``).

    Raises:
        ValueError: naming the field.
    """
    def valid(name: str, ok: bool) -> None:
        if not ok:
            raise ValueError(f"{name}: {getattr(options, name)!r}")

    valid("project", isinstance(options.project, str)
          and PROJECT_NAME.fullmatch(options.project) is not None)
    valid("wireguard", options.wireguard in WIREGUARD_CHOICES)
    valid("sim", isinstance(options.sim, bool))
    try:
        ipaddress.ip_address(options.bind)
        bind_ok = isinstance(options.bind, str)
    except ValueError:
        bind_ok = False
    valid("bind", bind_ok)
    valid("https_port", options.https_port is None or (
        type(options.https_port) is int and 1 <= options.https_port <= 65535))
    valid("version", isinstance(options.version, str)
          and re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,127}", options.version) is not None)
    valid("replicas", type(options.replicas) is int
          and 1 <= options.replicas <= MAX_RELAY_REPLICAS)
