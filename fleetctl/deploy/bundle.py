"""The robot's export bundle (``fleetctl export NAME``): every file a robot operator copies.

Written for a robot running Ubuntu 24.04 with ROS 2 Jazzy from apt, amd64 or arm64
(docs/robot.md): the client runs either from a venv made with ``--system-site-packages``
on the robot's own rclpy, under systemd, or in the ``fleetctl/client`` image
(``--network host``, amd64 only: its ROS 2 comes from x86_64 PyPI wheels).

Values reach the templates raw and each goes through the filter of its file's format
(:mod:`fleetctl.deploy.render`: ``sh``, ``env``, ``unit``, ``md``, ``comment``, ``y``,
``wg``); ``compose.yaml`` is data dumped with ``yaml.safe_dump``. Shell lines built here
(``docker run``) quote every word with :func:`sh_quote`.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass, field
from pathlib import Path

import yaml

import fleetctl
from fleetctl.deploy.files import PUBLIC_FILE_MODE, SECRET_FILE_MODE, stamp
from fleetctl.deploy.fleet import DEFAULT_RMW_IMPLEMENTATION, Fleet, Robot
from fleetctl.deploy.render import (
    Escaped,
    FleetKeys,
    client_config,
    comment_text,
    env_assignment,
    render_template,
    robot_wireguard,
    server_url,
    server_urls,
)

EXECUTABLE_FILE_MODE = 0o755

# The robot's WireGuard interface. Not wg0: a robot often has a wg0 of its own already.
WIREGUARD_INTERFACE = "fleet0"
ROS_SETUP = "/opt/ros/jazzy/setup.bash"
VENV_DIR = "/opt/fleetctl"
ETC_DIR = "/etc/fleetctl"
STATE_DIR = "/var/lib/fleetctl"
WRAPPER_PATH = "/usr/local/bin/fleetctl-client"
CLIENT_UNIT = "fleetctl-client.service"
CLIENT_IMAGE = "fleetctl/client"
# Where the client image reads its config (its default CMD).
IMAGE_CONFIG = "/etc/fleetctl/robot/client.yaml"
FASTDDS_RMW = "rmw_fastrtps_cpp"  # the only RMW of the PyPI wheels, hence of the image

WG_FILE = "wg0.conf"
CLIENT_FILE = "client.yaml"
README_FILE = "README.md"
ENV_FILE = "fleetctl.env"
WRAPPER_FILE = "fleetctl-client"
COMPOSE_FILE = "compose.yaml"

# pyproject.toml's `ros` extra, for x86_64 robots without ROS from apt.
ROS_WHEELS = (
    "ros-jazzy-rclpy[fastrtps]>=7,<8",
    "ros-jazzy-std-msgs>=5,<6",
    "ros-jazzy-sensor-msgs>=5,<6",
    "ros-jazzy-geometry-msgs>=5,<6",
    "ros-jazzy-nav-msgs>=5,<6",
    "ros-jazzy-visualization-msgs>=5,<6",
    "pillow>=10,<14",
)


@dataclass(frozen=True)
class BundleFile:
    """One file of the bundle.

    Attributes:
        relpath: its path inside the bundle.
        data: its bytes (may hold the robot's private key: left out of the repr).
        mode: its permission bits (0o600 for secrets, 0o755 for scripts).
    """

    relpath: str
    data: bytes = field(repr=False)
    mode: int = PUBLIC_FILE_MODE

    @property
    def secret(self) -> bool:
        """Whether only the owner may read it."""
        return self.mode & 0o077 == 0


# --- escaping, one function per format --------------------------------------------------


def sh_quote(value: str) -> str:
    """Quote *value* as one POSIX shell word (bare when it needs no quotes)."""
    return shlex.quote(value)


def env_value(name: str, value: str | int) -> str:
    """Return ``NAME=VALUE`` for an env file read by systemd, docker and sh alike.

    Raises:
        ValueError: the name is not an environment variable name, or the value needs
            quoting (no quoting means the same thing to all three readers).
    """
    return str(env_assignment((name, value)))


# --- the generated files ----------------------------------------------------------------


def client_image(version: str = fleetctl.__version__) -> str:
    """The client image the container route runs, e.g. ``fleetctl/client:0.1.0``."""
    return f"{CLIENT_IMAGE}:{version}"


def robot_env(fleet: Fleet, robot: Robot) -> str:
    """Return ``fleetctl.env``: the robot's ROS 2 graph (domain, RMW) from ``fleet.yaml``."""
    environment = [("ROS_DOMAIN_ID", robot.ros_domain_id),
                   ("RMW_IMPLEMENTATION", robot.rmw_implementation)]
    return render_template(
        "robot/fleetctl.env.j2", robot_name=robot.name, fleet_name=fleet.name,
        environment=environment, fastdds=robot.rmw_implementation == FASTDDS_RMW)


def client_unit(fleet: Fleet, robot: Robot) -> str:
    """Return ``fleetctl-client.service``: the client under systemd, after the tunnel."""
    return render_template(
        "robot/fleetctl-client.service.j2",
        description=f"fleetctl robot client of {robot.name} (fleet {fleet.name})",
        interface=WIREGUARD_INTERFACE, env_file=f"{ETC_DIR}/{ENV_FILE}",
        wrapper=WRAPPER_PATH, state_dir=STATE_DIR)


def client_wrapper(robot: Robot) -> str:
    """Return ``fleetctl-client``: runs ``fleetctl client`` in the robot's ROS 2 env."""
    text = render_template(
        "robot/fleetctl-client.sh.j2", robot_name=robot.name,
        ros_setup=ROS_SETUP, venv=VENV_DIR, config=f"{ETC_DIR}/{CLIENT_FILE}")
    return shebang_first(text)


def shebang_first(text: str) -> str:
    """Move a ``#!`` line back to the top, above the digest line rendering put first
    (the kernel only reads a shebang on the first line)."""
    first, _, rest = text.partition("\n")
    if first.startswith("#!") or not rest.startswith("#!"):
        return text
    shebang, _, body = rest.partition("\n")
    return f"{shebang}\n{first}\n{body}"


def _container_overrides(robot: Robot) -> dict[str, str]:
    """Environment the image needs beyond ``fleetctl.env``: it only has Fast DDS."""
    if robot.rmw_implementation == FASTDDS_RMW:
        return {}
    return {"RMW_IMPLEMENTATION": FASTDDS_RMW}


def docker_run_args(robot: Robot, version: str = fleetctl.__version__) -> list[str]:
    """The ``docker run`` argument list of the container route (run in the bundle dir)."""
    args = ["docker", "run", "-d", "--name", "fleetctl-client", "--restart", "unless-stopped",
            "--network", "host", "--env-file", ENV_FILE]
    for name, value in _container_overrides(robot).items():
        args += ["-e", env_value(name, value)]
    args += ["-v", f"$PWD/{CLIENT_FILE}:{IMAGE_CONFIG}:ro", client_image(version)]
    return args


def docker_run_line(robot: Robot, version: str = fleetctl.__version__) -> Escaped:
    """:func:`docker_run_args` as one shell line (``$PWD`` left for the shell to expand):
    every word quoted with :func:`sh_quote`, so the line goes into the README as it is."""
    words = []
    for arg in docker_run_args(robot, version):
        if arg.startswith("$PWD/"):
            words.append(f'"$PWD"/{sh_quote(arg.removeprefix("$PWD/"))}')
        else:
            words.append(sh_quote(arg))
    return Escaped(" ".join(words))


def client_compose(fleet: Fleet, robot: Robot, version: str = fleetctl.__version__) -> str:
    """Return ``compose.yaml``: the client image on the host network (format 2.4, which
    Compose v1 ``docker-compose`` and the v2 plugin both read)."""
    service: dict[str, object] = {
        "image": client_image(version),
        "network_mode": "host",
        "restart": "unless-stopped",
        "env_file": [ENV_FILE],
    }
    overrides = _container_overrides(robot)
    if overrides:
        service["environment"] = overrides
    service["volumes"] = [f"./{CLIENT_FILE}:{IMAGE_CONFIG}:ro"]
    service["command"] = ["fleetctl", "client", "--config", IMAGE_CONFIG]
    doc = {"version": "2.4", "services": {"fleetctl-client": service}}
    header = (f"# The fleetctl client of robot {comment_text(robot.name)} in a container "
              f"(amd64 only). Generated by 'fleetctl export'.\n"
              "# Start: docker compose up -d   (Compose v1: docker-compose up -d)\n")
    # Stamped as every other file of the bundle: a new export into the same directory
    # replaces only what an earlier export wrote (fleetctl.deploy.export).
    return stamp(header + yaml.safe_dump(doc, sort_keys=False))


def robot_readme(fleet: Fleet, robot: Robot, *, wheel_name: str) -> str:
    """Return the README of robot's export bundle: what is in it and how to start it.

    Args:
        fleet: the fleet (with an endpoint).
        robot: the robot.
        wheel_name: file name of the fleetctl wheel in the bundle.

    Raises:
        ValueError: the fleet has no endpoint (check with
            :func:`fleetctl.deploy.fleet.require_endpoint` first).
    """
    if fleet.endpoint is None:
        raise ValueError("a robot bundle needs the fleet's endpoint")
    version = fleetctl.__version__
    return render_template(
        "client/README.md.j2",
        fleet_name=fleet.name,
        robot_name=robot.name,
        ip=str(robot.ip),
        endpoint=fleet.endpoint,
        mtu_bytes=robot.mtu_bytes,
        server_url=server_url(fleet),
        # With relay replicas client.yaml lists each (the README said only the first);
        # without, this is server_url.
        server_urls=", ".join(server_urls(fleet)),
        server_ip=str(fleet.server_ip),
        ros_domain_id=robot.ros_domain_id,
        rmw=robot.rmw_implementation,
        rmw_is_fastdds=robot.rmw_implementation == FASTDDS_RMW,
        default_rmw=DEFAULT_RMW_IMPLEMENTATION,
        iface=WIREGUARD_INTERFACE,
        wheel=f"./{wheel_name}",
        wheel_name=wheel_name,
        venv=VENV_DIR,
        etc=ETC_DIR,
        ros_setup=ROS_SETUP,
        wrapper=WRAPPER_PATH,
        unit=CLIENT_UNIT,
        image=client_image(version),
        image_archive=f"fleetctl-client-{version}.tar.gz",
        docker_run=docker_run_line(robot, version),
        ros_wheels=ROS_WHEELS,
        files={"wg": WG_FILE, "client": CLIENT_FILE, "env": ENV_FILE, "wrapper": WRAPPER_FILE,
               "compose": COMPOSE_FILE},
    )


def robot_bundle(fleet: Fleet, robot: Robot, keys: FleetKeys, wheel: Path) -> list[BundleFile]:
    """Return every file of robot *robot*'s bundle (docs/robot.md).

    Args:
        fleet: the fleet.
        robot: the robot.
        keys: key material (the robot's and the server's).
        wheel: a fleetctl wheel to ship (see :func:`fleetctl.deploy.selfwheel.fleetctl_wheel`).

    Raises:
        ConfigError: the fleet has no keys for the robot.
        OSError: the wheel cannot be read.
    """
    def text(relpath: str, content: str, mode: int = PUBLIC_FILE_MODE) -> BundleFile:
        return BundleFile(relpath, content.encode("utf-8"), mode)

    return [
        text(WG_FILE, robot_wireguard(fleet, robot, keys), SECRET_FILE_MODE),
        text(CLIENT_FILE, client_config(fleet, robot)),
        text(ENV_FILE, robot_env(fleet, robot)),
        text(CLIENT_UNIT, client_unit(fleet, robot)),
        text(WRAPPER_FILE, client_wrapper(robot), EXECUTABLE_FILE_MODE),
        text(COMPOSE_FILE, client_compose(fleet, robot)),
        text(README_FILE, robot_readme(fleet, robot, wheel_name=wheel.name)),
        BundleFile(wheel.name, wheel.read_bytes()),
    ]
