"""A docker compose deployment of a fleet directory: render, up, down, status, logs.

The compose file is generated from the fleet directory layout of docs/design.md section 6
(``server/``, ``robots/NAME/``), written to ``FLEET/.compose/docker-compose.yml`` with the
files the containers need (a server.yaml with container paths, robot WireGuard configs whose
``Endpoint`` is the server container) and run with whichever Compose is installed.

Networking has two modes, both keeping the server's IP identity of robots real:

- WireGuard (default when ``/dev/net/tun`` exists): server and robots run ``wireguard-go``
  with the configs ``fleetctl`` generated; robots reach ``10.8.0.1`` through the tunnel.
- plain (``--wireguard off``, or no TUN device): the compose network *is* the fleet subnet;
  each robot container gets its fleet address, so the auth map still matches. ``up`` says so
  loudly.

The file format is Compose "2.4", which both Debian's ``docker-compose`` v1 and the
``docker compose`` v2 plugin accept (v1 cannot read the newer unversioned format's
``depends_on`` conditions).
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
import shutil
import subprocess
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from fleetctl import __version__
from fleetctl.deploy.dockercli import check, subprocess_runner
from fleetctl.deploy.images import image_tag
from fleetctl.errors import ConfigError, EnvironmentMissing, FleetError
from fleetctl.yamlfile import read_yaml

Progress = Callable[[str], None]
COMPOSE_DIR = ".compose"
COMPOSE_FILE = "docker-compose.yml"
SERVER_ETC = "/etc/fleetctl/server"
ROBOT_ETC = "/etc/fleetctl/robot"


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
class ComposePlan:
    """Everything needed to render and run one fleet's compose project.

    Attributes:
        fleet_dir: The fleet directory.
        project: Compose project name (container name prefix).
        wireguard: Run robots over WireGuard (else the plain network, see module doc).
        wireguard_note: Why that mode was chosen, shown to the user.
        robots: The robots, in name order.
        server_port: Server WebSocket/HTTP port inside the network.
        webviz_port: Webviz HTTP port (published on 127.0.0.1).
        wireguard_port: Server WireGuard UDP port.
        fleet_subnet: The fleet subnet (``10.8.0.0/24``).
        server_ip: The server's fleet address.
        version: Image tag.
        sim: Run the simulated robot next to each client.
    """

    fleet_dir: Path
    project: str
    wireguard: bool
    wireguard_note: str
    robots: tuple[RobotEntry, ...]
    server_port: int = 8080
    webviz_port: int = 8000
    wireguard_port: int = 51820
    fleet_subnet: str = "10.8.0.0/24"
    server_ip: str = "10.8.0.1"
    version: str = __version__
    sim: bool = True

    @property
    def compose_dir(self) -> Path:
        """``FLEET/.compose``."""
        return self.fleet_dir / COMPOSE_DIR

    @property
    def compose_file(self) -> Path:
        """The generated compose file."""
        return self.compose_dir / COMPOSE_FILE


@dataclass(frozen=True)
class UpResult:
    """What ``up`` did."""

    compose_file: Path
    wireguard_note: str


def compose_command(runner: Callable[..., Any] = subprocess_runner) -> list[str]:
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


def _read_server_config(path: Path) -> dict[str, Any]:
    data = read_yaml(path, "server config")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return data


def _wg_value(conf: Path, key: str) -> str | None:
    try:
        text = conf.read_text()
    except OSError:
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


def _project_name(fleet_dir: Path) -> str:
    name = re.sub(r"[^a-z0-9]+", "", fleet_dir.resolve().name.lower()) or "fleet"
    return f"fleetctl{name}"


def wireguard_mode(requested: str, tun: Path = Path("/dev/net/tun")) -> tuple[bool, str]:
    """Decide WireGuard on/off from ``auto|on|off`` and whether the TUN device exists.

    Raises:
        FleetError: bad *requested*, or ``on`` without a TUN device.
    """
    if requested not in ("auto", "on", "off"):
        raise FleetError(f"--wireguard must be auto, on or off, not {requested!r}")
    if requested == "off":
        return False, "off (requested): robots use the plain network with their fleet IPs"
    if tun.exists():
        return True, "on: wireguard-go in the server and robot containers"
    if requested == "on":
        raise EnvironmentMissing(f"--wireguard on, but {tun} does not exist on this host")
    return False, (
        f"WARNING: WireGuard NOT used: {tun} is missing on this host; robots use the plain "
        "network with their fleet IPs"
    )


def plan_for(
    fleet_dir: Path, *, wireguard: str = "auto", project: str | None = None, sim: bool = True
) -> ComposePlan:
    """Read the fleet directory and decide the deployment.

    Raises:
        ConfigError: the fleet directory, a config or a WireGuard config is missing or bad
            (the message names file and field).
    """
    fleet_dir = fleet_dir.resolve()
    if not (fleet_dir / "fleet.yaml").is_file():
        raise ConfigError(f"{fleet_dir / 'fleet.yaml'}: missing; is this a fleet directory?")
    server = _read_server_config(fleet_dir / "server" / "server.yaml")
    port = server.get("listen_port", 8080)
    if not isinstance(port, int) or not 0 < port < 65536:
        raise ConfigError(f"{fleet_dir / 'server/server.yaml'}: field listen_port: bad port")
    robots = []
    robots_dir = fleet_dir / "robots"
    for robot_dir in sorted(robots_dir.iterdir()) if robots_dir.is_dir() else []:
        if (robot_dir / "client.yaml").is_file():
            robots.append(RobotEntry(robot_dir.name, _robot_ip(robot_dir), robot_dir))
    wg_on, note = wireguard_mode(wireguard)
    wg_port = _wg_value(fleet_dir / "server" / "wireguard" / "wg0.conf", "ListenPort")
    server_addr = _wg_value(fleet_dir / "server" / "wireguard" / "wg0.conf", "Address")
    return ComposePlan(
        fleet_dir=fleet_dir,
        project=project or _project_name(fleet_dir),
        wireguard=wg_on,
        wireguard_note=note,
        robots=tuple(robots),
        server_port=port,
        wireguard_port=int(wg_port) if wg_port and wg_port.isdigit() else 51820,
        server_ip=str(ipaddress.ip_interface(server_addr).ip) if server_addr else "10.8.0.1",
        fleet_subnet=str(ipaddress.ip_interface(server_addr).network)
        if server_addr
        else "10.8.0.0/24",
        sim=sim,
    )


def _server_service(plan: ComposePlan) -> dict[str, Any]:
    svc: dict[str, Any] = {
        "image": image_tag("server", plan.version),
        "command": ["fleetctl", "server", "--config", f"{SERVER_ETC}/server.yaml"],
        "volumes": [
            f"{plan.compose_dir / 'server'}:{SERVER_ETC}:ro",
            "server-data:/var/lib/fleetctl",
        ],
        "environment": {"FLEETCTL_HEALTH": f"http://127.0.0.1:{plan.server_port}/healthz"},
        "restart": "unless-stopped",
        "networks": {"fleet": _static(plan, plan.server_ip)},
    }
    if plan.wireguard:
        svc.update(_wg_privileges(f"{SERVER_ETC}/wg0.conf"))
    return svc


def _static(plan: ComposePlan, ip: str) -> dict[str, str] | None:
    # Plain mode: the compose network is the fleet subnet, so robots keep their identity.
    return None if plan.wireguard else {"ipv4_address": ip}


def _wg_privileges(conf: str) -> dict[str, Any]:
    # wireguard-go needs root, NET_ADMIN and the TUN device; the entrypoint drops to the
    # fleetctl user once the tunnel is up.
    return {
        "user": "root",
        "cap_add": ["NET_ADMIN"],
        "devices": ["/dev/net/tun:/dev/net/tun"],
        "environment_wg": {"WG_CONFIG": conf, "WG_REQUIRED": "1"},
    }


def _robot_service(plan: ComposePlan, robot: RobotEntry) -> dict[str, Any]:
    client = f"fleetctl client --config {ROBOT_ETC}/client.yaml"
    sim = (
        "python3 -c 'import sys; from fleetctl.client.ros.sim import SimConfig, run_sim; "
        f"run_sim(SimConfig(name=sys.argv[1]))' {robot.name} & "
        if plan.sim
        else ""
    )
    svc: dict[str, Any] = {
        "image": image_tag("client", plan.version),
        "command": ["bash", "-c", f"{sim}exec {client}"],
        "volumes": [f"{robot.robot_dir}:{ROBOT_ETC}:ro"],
        "environment": {
            # Each robot's ROS graph stays inside its container: everything between robots
            # goes through the server, as on real robots.
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        },
        "depends_on": {"server": {"condition": "service_healthy"}},
        "restart": "unless-stopped",
        "networks": {"fleet": _static(plan, robot.fleet_ip)},
    }
    if plan.wireguard:
        svc["volumes"].append(f"{plan.compose_dir / 'robots' / robot.name}:/etc/fleetctl/wg:ro")
        svc.update(_wg_privileges("/etc/fleetctl/wg/wg0.conf"))
    return svc


def _webviz_service(plan: ComposePlan) -> dict[str, Any]:
    return {
        "image": image_tag("webviz", plan.version),
        "command": ["fleetctl", "webviz", "--host", "0.0.0.0", "--port", str(plan.webviz_port)],
        "environment": {"FLEETCTL_HEALTH": f"http://127.0.0.1:{plan.webviz_port}/"},
        "ports": [f"127.0.0.1:{plan.webviz_port}:{plan.webviz_port}"],
        "restart": "unless-stopped",
        "networks": {"fleet": None},
    }


def render(plan: ComposePlan) -> dict[str, Any]:
    """The compose document of *plan* (pure: no files touched)."""
    services: dict[str, Any] = {"server": _server_service(plan), "webviz": _webviz_service(plan)}
    for robot in plan.robots:
        services[f"robot-{robot.name}"] = _robot_service(plan, robot)
    for svc in services.values():
        env = svc.pop("environment_wg", None)
        if env:
            svc["environment"] = {**svc.get("environment", {}), **env}
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
        "volumes": {"server-data": {}},
    }


def write_files(plan: ComposePlan) -> Path:
    """Write the compose file and the container-side configs under ``FLEET/.compose``."""
    out = plan.compose_dir
    (out / "server").mkdir(parents=True, exist_ok=True)
    os.chmod(out, 0o700)  # holds copies of WireGuard private keys
    _write_server_config(plan, out / "server")
    for robot in plan.robots:
        if plan.wireguard:
            _write_robot_wg(plan, robot, out / "robots" / robot.name)
    plan.compose_file.write_text(
        "# Generated by `fleetctl up` from the fleet directory; do not edit.\n"
        + yaml.safe_dump(render(plan), sort_keys=False)
    )
    return plan.compose_file


def _write_server_config(plan: ComposePlan, out: Path) -> None:
    src = plan.fleet_dir / "server"
    cfg = _read_server_config(src / "server.yaml")
    cfg["listen_host"] = "0.0.0.0"
    # The config directory is mounted read-only; the database lives in a named volume.
    cfg["database"] = "/var/lib/fleetctl/fleet.db"
    auth = cfg.get("auth_map", "auth.yaml")
    shutil.copy2(src / str(auth), out / "auth.yaml")
    cfg["auth_map"] = f"{SERVER_ETC}/auth.yaml"
    for key in ("tls_cert", "tls_key"):
        if cfg.get(key):
            shutil.copy2(src / str(cfg[key]), out / Path(str(cfg[key])).name)
            cfg[key] = f"{SERVER_ETC}/{Path(str(cfg[key])).name}"
    (out / "server.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    wg = src / "wireguard" / "wg0.conf"
    if plan.wireguard:
        _copy_secret(wg.read_text(), out / "wg0.conf")


def _write_robot_wg(plan: ComposePlan, robot: RobotEntry, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    text = (robot.robot_dir / "wireguard" / "wg0.conf").read_text()
    # Inside compose the server is reached by its service name, whatever public endpoint
    # fleet.yaml names for real robots.
    text = re.sub(r"(?m)^(\s*Endpoint\s*=\s*).*$", rf"\g<1>server:{plan.wireguard_port}", text)
    _copy_secret(text, out / "wg0.conf")


def _copy_secret(text: str, dest: Path) -> None:
    fd = os.open(dest, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.chmod(dest, 0o600)


def _compose(plan: ComposePlan, *args: str) -> list[str]:
    return [*compose_command(), "-p", plan.project, "-f", str(plan.compose_file), *args]


def up(plan: ComposePlan, progress: Progress = print) -> UpResult:
    """Render and start the deployment (detached); returns where the file is.

    Raises:
        FleetError: compose failed (its output is shown).
    """
    progress(f"wireguard: {plan.wireguard_note}")
    path = write_files(plan)
    progress(f"compose file {path}; starting {len(plan.robots)} robot(s)")
    check(subprocess_runner(_compose(plan, "up", "-d"), None, False), "compose up")
    return UpResult(path, plan.wireguard_note)


def existing(fleet_dir: Path, *, project: str | None = None) -> ComposePlan:
    """The plan of a deployment ``up`` already rendered (for down, status, logs).

    Raises:
        FleetError: nothing was rendered in *fleet_dir*.
    """
    fleet_dir = fleet_dir.resolve()
    path = fleet_dir / COMPOSE_DIR / COMPOSE_FILE
    if not path.is_file():
        raise FleetError(f"{path}: missing; run `fleetctl up {fleet_dir}` first")
    return ComposePlan(fleet_dir, project or _project_name(fleet_dir), False, "", ())


def down(plan: ComposePlan, progress: Progress = print) -> None:
    """Stop and remove the containers, networks and the server's data volume."""
    progress(f"stopping {plan.project}")
    check(subprocess_runner(_compose(plan, "down", "-v", "--remove-orphans"), None, False),
          "compose down")


def logs(plan: ComposePlan, services: Sequence[str], *, follow: bool) -> int:
    """Print the logs (following when *follow*); returns compose's exit code."""
    args = ["logs", "--no-color", *(["-f"] if follow else []), *services]
    return subprocess.run(_compose(plan, *args), check=False).returncode


@dataclass(frozen=True)
class ServiceState:
    """One container: its service, run state and health (``none`` without a check)."""

    service: str
    state: str
    health: str


@dataclass(frozen=True)
class StatusReport:
    """Services' states and the server's robot list (``None``: the server did not answer)."""

    services: tuple[ServiceState, ...]
    robots: list[dict[str, Any]] | None
    robots_error: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict."""
        return {
            "services": [s.__dict__ for s in self.services],
            "robots": self.robots,
            "robots_error": self.robots_error or None,
        }

    def render_text(self) -> str:
        """A plain-text table."""
        lines = [f"{'SERVICE':<24} {'STATE':<10} HEALTH"]
        lines += [f"{s.service:<24} {s.state:<10} {s.health}" for s in self.services]
        lines.append("")
        if self.robots is None:
            lines.append(f"robots: unknown ({self.robots_error})")
        else:
            lines.append(f"{'ROBOT':<24} {'ONLINE':<7} LAST SEEN")
            for r in self.robots:
                lines.append(
                    f"{r.get('name', '?')!s:<24} {'yes' if r.get('online') else 'no':<7} "
                    f"{r.get('last_seen', '-')}"
                )
        return "\n".join(lines)


def status(plan: ComposePlan) -> StatusReport:
    """Each container's state and health, and the robots as the server reports them."""
    ids = check(subprocess_runner(_compose(plan, "ps", "-q"), None, True), "compose ps")
    services = []
    server_id = None
    for cid in ids.stdout.split():
        res = subprocess_runner(["docker", "inspect", cid], None, True)
        if res.returncode != 0:
            continue
        info = json.loads(res.stdout)[0]
        name = info["Config"]["Labels"].get("com.docker.compose.service", cid[:12])
        health = info["State"].get("Health", {}).get("Status", "none")
        services.append(ServiceState(name, info["State"]["Status"], health))
        server_id = cid if name == "server" else server_id
    robots, error = _server_robots(server_id)
    return StatusReport(tuple(sorted(services, key=lambda s: s.service)), robots, error)


_ROBOTS_SNIPPET = (
    "import os,urllib.request;u=os.environ['FLEETCTL_HEALTH'].rsplit('/',1)[0]+'/robots';"
    "print(urllib.request.urlopen(u,timeout=3).read().decode())"
)


def _server_robots(server_id: str | None) -> tuple[list[dict[str, Any]] | None, str]:
    if server_id is None:
        return None, "no server container"
    # Asked from inside the server container: /robots answers loopback without a token.
    res = subprocess_runner(["docker", "exec", server_id, "python3", "-c", _ROBOTS_SNIPPET],
                            None, True)
    if res.returncode != 0:
        return None, (res.stderr.strip().splitlines() or ["server did not answer"])[-1]
    try:
        data = json.loads(res.stdout)
    except json.JSONDecodeError:
        return None, "server /robots is not JSON"
    robots = data.get("robots", data) if isinstance(data, dict) else data
    return (robots if isinstance(robots, list) else None), ""
