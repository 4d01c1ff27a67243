"""Render every artifact of a fleet from jinja2 templates (``StrictUndefined``).

Rendering is a pure function of the :class:`~fleetctl.deploy.fleet.Fleet` and its keys:
the same inputs give the same bytes, so re-rendering an unchanged fleet writes nothing.
"""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import jinja2

from fleetctl.deploy import auth
from fleetctl.deploy.files import Plan
from fleetctl.deploy.fleet import Fleet, Robot
from fleetctl.deploy.keys import public_key
from fleetctl.deploy.keystore import RobotKeys
from fleetctl.deploy.secrets import Secret
from fleetctl.deploy.topics import DEFAULT_PUBLISH
from fleetctl.errors import ConfigError, EnvironmentMissing

TEMPLATES_ENV = "FLEETCTL_TEMPLATES"  # overrides where templates/ is looked up


@dataclass(frozen=True)
class FleetKeys:
    """All key material a fleet's artifacts need."""

    server_private_key: Secret
    robots: Mapping[str, RobotKeys]

    def robot(self, name: str) -> RobotKeys:
        """Return robot *name*'s keys.

        Raises:
            ConfigError: if the fleet has no keys for it.
        """
        try:
            return self.robots[name]
        except KeyError:
            raise ConfigError(f"no keys for robot {name!r}") from None


@dataclass(frozen=True)
class Artifact:
    """One rendered file, its path relative to its root, and whether it holds a secret."""

    relpath: str
    text: str
    secret: bool = False


def templates_dir() -> Path:
    """Return the ``templates/`` directory (``$FLEETCTL_TEMPLATES`` overrides)."""
    override = os.environ.get(TEMPLATES_ENV)
    if override:
        return Path(override)
    return Path(__file__).resolve().parents[2] / "templates"


def _yaml_scalar(value: object) -> str:
    """Format a scalar for YAML; JSON scalars are valid YAML flow scalars, quotes included."""
    if not isinstance(value, str | int | float | bool) and value is not None:
        raise TypeError(f"not a YAML scalar: {type(value).__name__}")
    return json.dumps(value)


@functools.cache
def _environment(root: Path) -> jinja2.Environment:
    if not root.is_dir():
        raise EnvironmentMissing(f"templates directory {root} not found (set {TEMPLATES_ENV})")
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(root)),
        undefined=jinja2.StrictUndefined,
        autoescape=False,  # configs, not HTML
        keep_trailing_newline=True,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["y"] = _yaml_scalar
    return env


def render_template(name: str, **context: object) -> str:
    """Render one template; a missing variable is an error, never an empty string."""
    try:
        return _environment(templates_dir()).get_template(name).render(**context)
    except jinja2.TemplateNotFound:
        raise EnvironmentMissing(f"template {templates_dir() / name} not found") from None


def server_wireguard(fleet: Fleet, keys: FleetKeys) -> str:
    """Return the server's ``wg0.conf``: one ``[Peer]`` with a /32 per robot."""
    peers = [
        {
            "name": r.name,
            "ip": str(r.ip),
            "public_key": public_key(keys.robot(r.name).private_key, f"key of robot {r.name}"),
            "preshared_key": keys.robot(r.name).preshared_key.reveal(),
        }
        for r in fleet.robots
    ]
    return render_template(
        "wireguard/server.conf.j2",
        fleet_name=fleet.name,
        server_ip=str(fleet.server_ip),
        prefix_len=fleet.subnet.prefixlen,
        listen_port=fleet.wireguard_port,
        private_key=keys.server_private_key.reveal(),
        peers=peers,
    )


def robot_wireguard(fleet: Fleet, robot: Robot, keys: FleetKeys) -> str:
    """Return robot's ``wg0.conf``: its /32, the server as the only peer."""
    robot_keys = keys.robot(robot.name)
    return render_template(
        "wireguard/robot.conf.j2",
        fleet_name=fleet.name,
        robot_name=robot.name,
        ip=str(robot.ip),
        mtu_bytes=robot.mtu_bytes,
        private_key=robot_keys.private_key.reveal(),
        preshared_key=robot_keys.preshared_key.reveal(),
        server_public_key=public_key(keys.server_private_key, "server key"),
        endpoint=fleet.endpoint,
        subnet=str(fleet.subnet),
    )


def server_url(fleet: Fleet) -> str:
    """Return the WebSocket URL robots reach the server on (through the tunnel)."""
    return f"ws://{fleet.server_ip}:{fleet.server_port}/"


def client_config(fleet: Fleet, robot: Robot) -> str:
    """Return robot's ``client.yaml`` with the default mobile-robot topic set."""
    subscribe = [
        {"remote_topic": f"/{robot.name}/{c.topic}", "type": c.type, "local_topic": f"/{c.topic}"}
        for c in robot.command_topics
    ]
    return render_template(
        "client/client.yaml.j2",
        fleet_name=fleet.name,
        robot_name=robot.name,
        server_url=server_url(fleet),
        bind_address=str(robot.ip),
        publish=DEFAULT_PUBLISH,
        subscribe=subscribe,
    )


def robot_readme(fleet: Fleet, robot: Robot) -> str:
    """Return the README of robot's export bundle: what is in it and how to start it."""
    return render_template(
        "client/README.md.j2",
        fleet_name=fleet.name,
        robot_name=robot.name,
        ip=str(robot.ip),
        endpoint=fleet.endpoint,
        mtu_bytes=robot.mtu_bytes,
        server_url=server_url(fleet),
        server_ip=str(fleet.server_ip),
    )


def auth_map(fleet: Fleet) -> str:
    """Return ``auth.yaml`` (docs/design.md section 3)."""
    return render_template("auth/auth.yaml.j2", fleet_name=fleet.name,
                           identities=auth.identities(fleet))


def server_config(fleet: Fleet) -> str:
    """Return ``server.yaml`` (docs/design.md section 4)."""
    return render_template("server/server.yaml.j2", fleet_name=fleet.name,
                           listen_port=fleet.server_port)


def robot_bundle(fleet: Fleet, robot: Robot, keys: FleetKeys) -> list[Artifact]:
    """Return the files robot *robot* needs: ``wg0.conf``, ``client.yaml``, ``README.md``."""
    return [
        Artifact("wg0.conf", robot_wireguard(fleet, robot, keys), secret=True),
        Artifact("client.yaml", client_config(fleet, robot)),
        Artifact("README.md", robot_readme(fleet, robot)),
    ]


def fleet_artifacts(fleet: Fleet, keys: FleetKeys) -> list[Artifact]:
    """Return every generated file of the fleet directory (docs/design.md section 6)."""
    out = [
        Artifact("server/server.yaml", server_config(fleet)),
        Artifact("server/auth.yaml", auth_map(fleet)),
        Artifact("server/wireguard/wg0.conf", server_wireguard(fleet, keys), secret=True),
    ]
    for robot in fleet.robots:
        out.append(Artifact(f"robots/{robot.name}/client.yaml", client_config(fleet, robot)))
        out.append(Artifact(f"robots/{robot.name}/wireguard/wg0.conf",
                            robot_wireguard(fleet, robot, keys), secret=True))
    return out


def plan_artifacts(plan: Plan, root: Path, artifacts: list[Artifact]) -> None:
    """Add writing *artifacts* under *root* to *plan* (secrets 0600 in 0700 dirs)."""
    for a in artifacts:
        plan.write(root / a.relpath, a.text, secret=a.secret)
