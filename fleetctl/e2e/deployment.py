"""The e2e fleet as ``fleetctl up`` deploys it.

fleetctl's own deploy code makes everything: :func:`~fleetctl.deploy.operations.create_fleet`,
``add_robot robot1`` and ``add_user`` (a viewer: the consumers' token) make a fleet directory
in the run's work directory (``WORK/fleet``, keys 0600 in 0700 directories);
:func:`~fleetctl.deploy.compose.plan_for` and :func:`~fleetctl.deploy.compose.write_files` write
what ``up`` writes (``WORK/fleet/.compose``: the container ``server.yaml``, the certificate,
the TLS key handed over through ``FLEETCTL_SECRETS``, the compose file itself for the
record); the server container is :func:`~fleetctl.deploy.compose.server_service` converted to
``docker run`` arguments (:mod:`fleetctl.deploy.dockerrun`). The fleet's endpoint is
``server:51820``, the compose service's name, which is also the server container's alias on
the server network and a name in the fleet's self-signed certificate.

What e2e changes in that service, each for a reason (:meth:`Deployment.server_service`):

- no ``ports``: nothing is published on the host; the run's traffic stays in its networks;
- ``restart: "no"``: a crash fails the run instead of being restarted unseen;
- its network is the run's server network, with no static fleet address (in the plain
  mode ``up`` gives the server ``10.8.0.1`` on a network that *is* the fleet subnet; here
  robots are routed from their own network);
- the topology adds ``NET_ADMIN`` (it deletes every container's default route), the run's
  labels, name and the alias ``server``; the named volume ``server-data`` becomes an
  anonymous one (removed with the container); with ``--mount-source``, the checkout's
  package is mounted over the image's.

Robots stay e2e's load publisher plus the real client. Over WireGuard their ``wg0.conf`` is
:func:`~fleetctl.deploy.compose.robot_wireguard`'s (``Endpoint = server:51820``), mounted
where ``up`` mounts a simulated robot's, with the same ``WG_CONFIG``/``WG_REQUIRED``; the
name ``server`` resolves to the server container's address through ``--add-host`` (robots
are on the other network, where Docker's DNS does not answer for it). Without WireGuard
(``--wireguard off``) the auth map the server reads is the fleet's with one change: robot1
is the robot network's CIDR instead of its fleet address (``e2e-auth.yaml`` beside the
container ``server.yaml``): the robot is routed, not NATed, so the server sees its container
address.

Consumers are the operators' side: they reach the server as people do, on the HTTPS port
(``wss://``, the fleet's certificate checked, the viewer's Bearer token).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from fleetctl.deploy import compose, operations
from fleetctl.deploy.secrets import Secret
from fleetctl.e2e import profiles
from fleetctl.e2e.wireguard import WG_PORT, choose_subnet
from fleetctl.errors import FleetError
from fleetctl.yamlfile import read_yaml

SERVER_ALIAS = "server"  # the compose service's name, and the robots' Endpoint host
CONSUMER_EMAIL = "e2e-consumer@example.org"
ROBOT_WG_DIR = "/etc/fleetctl/wg"  # where `up` mounts a simulated robot's wg0.conf
WG_IFACE = compose.WG_INTERFACE  # the entrypoint names the interface after the config
E2E_AUTH = "e2e-auth.yaml"
SITE_PACKAGE = "/opt/fleetctl/lib/python3.11/site-packages/fleetctl"


@dataclass
class Deployment:
    """The fleet directory and ``up``'s files for one run.

    Args:
        work: The run's work directory (host side).
        run_id: The run's id.
        wireguard: Robots reach the server through WireGuard (else the routed network).
        mtu_bytes: The robot's tunnel MTU (``add_robot --mtu``).
        source_dir: A checkout whose ``fleetctl/`` is mounted over the images' package.
    """

    work: Path
    run_id: str
    wireguard: bool
    mtu_bytes: int
    source_dir: Path | None = None
    _plan: compose.ComposePlan | None = field(default=None, repr=False)
    _token: Secret | None = field(default=None, repr=False)

    @property
    def fleet_dir(self) -> Path:
        """The fleet directory ``create_fleet`` made."""
        return self.work / "fleet"

    @property
    def plan(self) -> compose.ComposePlan:
        """``up``'s plan of the fleet.

        Raises:
            FleetError: :meth:`create` has not run.
        """
        if self._plan is None:
            raise FleetError("the e2e fleet is not created yet")
        return self._plan

    @property
    def token(self) -> str:
        """The consumers' (viewer's) token."""
        if self._token is None:
            raise FleetError("the e2e fleet is not created yet")
        return self._token.reveal()

    @property
    def robot_vpn_ip(self) -> str:
        """robot1's fleet (WireGuard) address."""
        return operations.robot_address(self.fleet_dir, profiles.ROBOT).compressed

    def create(self, avoid: Sequence[str], robot_cidr: str) -> None:
        """Make the fleet, write ``up``'s files, the robot's and the consumers' files.

        Args:
            avoid: CIDRs the fleet subnet must not overlap (the run's Docker networks).
            robot_cidr: The robot network (robot1's identity without WireGuard).
        """
        shutil.rmtree(self.fleet_dir, ignore_errors=True)
        operations.create_fleet(
            self.fleet_dir, endpoint=f"{SERVER_ALIAS}:{WG_PORT}", name=f"e2e-{self.run_id}",
            subnet=choose_subnet(avoid), wireguard_port=WG_PORT)
        operations.add_robot(self.fleet_dir, profiles.ROBOT, mtu_bytes=self.mtu_bytes)
        self._token = operations.add_user(self.fleet_dir, CONSUMER_EMAIL, "viewer").token
        self._plan = compose.plan_for(self.fleet_dir, compose.Options(
            project=f"fce2e{self.run_id}", wireguard="on" if self.wireguard else "off"))
        compose.write_files(self._plan)
        if self.wireguard:
            robot = self._robot_entry()
            _write(self.robot_wg_dir / "wg0.conf", compose.robot_wireguard(self._plan, robot),
                   0o600)
        else:
            self._routed_auth(robot_cidr)
        # Consumers run as the images' unprivileged user: public files in the work dir.
        _write(self.work / "tls-cert.pem", self._plan.tls_cert.read_text(), 0o644)
        _write(self.work / "token", self.token, 0o644)  # a test's token, for a test's users

    @property
    def robot_wg_dir(self) -> Path:
        """Host directory of the robot's ``wg0.conf`` (compose's place for it)."""
        return self.plan.compose_dir / "robots" / profiles.ROBOT

    def _robot_entry(self) -> compose.RobotEntry:
        (robot,) = [r for r in self.plan.robots if r.name == profiles.ROBOT]
        return robot

    def _routed_auth(self, robot_cidr: str) -> None:
        """Plain mode: the fleet's auth map, robot1 named by the robot network's CIDR."""
        self._write_routed_auth(robot_cidr)
        run_dir = self.plan.compose_dir / "server"
        cfg = read_yaml(run_dir / "server.yaml", "container server config")
        cfg["auth_map"] = f"{compose.RUN_ETC}/{E2E_AUTH}"
        _write(run_dir / "server.yaml", yaml.safe_dump(cfg, sort_keys=False), 0o644)

    def _write_routed_auth(self, robot_cidr: str) -> None:
        auth = read_yaml(self.fleet_dir / "server" / "auth.yaml", "auth map")
        for identity in auth["identities"]:
            if identity["name"] == profiles.ROBOT:
                identity.pop("ip", None)
                identity["cidr"] = robot_cidr
        _write(self.plan.compose_dir / "server" / E2E_AUTH,
               yaml.safe_dump(auth, sort_keys=False), 0o644)

    def replica_service(self, name: str, cluster: dict[str, Any],
                        robot_cidr: str) -> dict[str, Any]:
        """A relay replica (issue 15): the server service with a ``cluster:`` section.

        Replicas are reached on the routed network (robot1 named by the robot network's
        CIDR, listening on every address) whatever ``--wireguard`` says: the fleet's
        tunnel ends in the one server container, and a robot that fails over must reach
        the other replica. Everything else is ``up``'s server (image, TLS listener, the
        secrets' hand-over, the health check).
        """
        self._write_routed_auth(robot_cidr)
        run_dir = self.plan.compose_dir / "server"
        cfg = read_yaml(run_dir / "server.yaml", "container server config")
        cfg["auth_map"] = f"{compose.RUN_ETC}/{E2E_AUTH}"
        cfg["listen_host"] = "0.0.0.0"
        cfg["cluster"] = {"name": name, **cluster}
        config_name = f"replica-{name}.yaml"
        _write(run_dir / config_name, yaml.safe_dump(cfg, sort_keys=False), 0o644)
        svc = self.server_service()
        svc["command"] = ["fleetctl", "server", "--config", f"{compose.RUN_ETC}/{config_name}"]
        for key in ("WG_CONFIG", "WG_REQUIRED"):
            svc["environment"].pop(key, None)
        svc.pop("devices", None)
        return svc

    def server_service(self) -> dict[str, Any]:
        """``up``'s server service with e2e's changes (the module doc says why each)."""
        svc = compose.server_service(self.plan)
        svc.pop("ports", None)
        svc["restart"] = "no"
        svc["networks"] = ["fleet"]
        if self.source_dir is not None:
            svc["volumes"].append(f"{self.source_dir / 'fleetctl'}:{SITE_PACKAGE}:ro")
        return svc

    def robot_options(self, server_ip: str) -> dict[str, Any]:
        """``Topology.start`` arguments of a robot container (WireGuard as ``up`` sets a
        simulated robot's up; nothing without WireGuard)."""
        if not self.wireguard:
            return {}
        return {"env": {"WG_CONFIG": f"{ROBOT_WG_DIR}/wg0.conf", "WG_REQUIRED": "1"},
                "user": "root", "devices": [str(compose.TUN_DEVICE)],
                "mounts": [f"{self.robot_wg_dir}:{ROBOT_WG_DIR}:ro"],
                "hosts": {SERVER_ALIAS: server_ip}}

    def robot_url(self, server_ip: str) -> str:
        """The plain ``ws://`` URL robots use: the server's fleet address through the
        tunnel, else its address on the server network."""
        host = self.plan.server_ip if self.wireguard else server_ip
        return f"ws://{host}:{self.plan.server_port}/"

    def loopback_url(self) -> str:
        """The plain ``ws://`` URL of the relay's listener on loopback, for a process in
        the server's own network namespace (``up`` binds the plain listener there too)."""
        return f"ws://127.0.0.1:{self.plan.server_port}/"

    def consumer_url(self, server_ip: str) -> str:
        """The ``wss://`` URL of the HTTPS listener on the server network."""
        return f"wss://{server_ip}:{self.plan.https_port}/"


def _write(path: Path, text: str, mode: int) -> None:
    # A secret (mode 0600) goes in a 0700 directory, as compose's own copies do.
    path.parent.mkdir(mode=0o700 if mode == 0o600 else 0o755, parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    path.chmod(mode)
