"""The e2e fleet over WireGuard, as ``fleetctl up`` deploys it.

Keys and configs come from fleetctl's own deploy code: :func:`create_fleet` and
:func:`add_robot` make a fleet directory in the run's work directory (``WORK/fleet``, keys
0600 in 0700 directories), and :func:`render_fleet` re-renders the robot's ``wg0.conf`` once
the server container's address is known (its ``Endpoint``: the server container on the
server network, so the tunnel's UDP packets cross the router and its shaping). The image
entrypoint (``images/entrypoint.sh``) brings ``wireguard-go`` up from ``WG_CONFIG`` (root,
``NET_ADMIN``, ``/dev/net/tun``), then drops to the ``fleetctl`` user.

One robot identity (``robot1``, one key, one VPN address) serves every robot container of a
run: they run one after another, and each new container makes a fresh handshake from its own
address (WireGuard roaming). The server's auth map names the robot by that VPN address.

Interface names are unique per container (``fs-RUN`` for the server, ``fr-RUN-N`` for
robots): ``wireguard-go``'s UAPI socket path is not per network namespace.

MTU: the tunnel's is the link's minus 80 bytes (WireGuard's own rule: 40-byte IPv6 outer
header, 8 UDP, 32 WireGuard), so an encrypted packet is never fragmented by the router and
always fits the shaper's bucket.
"""

from __future__ import annotations

import ipaddress
import os
import re
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from fleetctl.deploy import operations
from fleetctl.deploy.files import Plan
from fleetctl.deploy.fleet import dump_fleet, fleet_file, load_fleet
from fleetctl.e2e import profiles
from fleetctl.errors import EnvironmentMissing, FleetError

TUN_DEVICE = Path("/dev/net/tun")
WG_PORT = 51820
OVERHEAD_BYTES = 80
FLEETCTL_HOME = "/var/lib/fleetctl"  # the images' fleetctl user's home
# VPN subnets to try, first one that overlaps no Docker network of the run wins.
_SUBNETS = ("10.8.0.0/24", "10.88.0.0/24", "172.30.250.0/24", "192.168.250.0/24")
# create_fleet needs an endpoint before the server container (and its address) exists.
_PLACEHOLDER_HOST = "server.invalid"


@dataclass(frozen=True)
class Mode:
    """Whether the run uses WireGuard, and why (the report's ``wireguard`` line)."""

    on: bool
    why: str

    def describe(self) -> str:
        """``on: ...`` or ``off: ...``."""
        return f"{'on' if self.on else 'off'}: {self.why}"


def decide(requested: str, tun: Path = TUN_DEVICE) -> Mode:
    """Decide from ``--wireguard auto|on|off`` and whether *tun* exists.

    Raises:
        FleetError: *requested* is not auto, on or off.
        EnvironmentMissing: ``on`` without a TUN device.
    """
    if requested not in ("auto", "on", "off"):
        raise FleetError(f"--wireguard must be auto, on or off, not {requested!r}")
    if requested == "off":
        return Mode(False, "--wireguard off; robots reach the server over the routed network")
    if tun.exists():
        return Mode(True, f"--wireguard {requested} and {tun} exists; wireguard-go in the "
                    "server and robot containers, robots reach the server through the tunnel")
    if requested == "on":
        raise EnvironmentMissing(f"--wireguard on, but {tun} does not exist on this host")
    return Mode(False, f"{tun} is missing on this host; robots reach the server over the "
                "routed network")


def tunnel_mtu(link_mtu_bytes: int) -> int:
    """The tunnel MTU (bytes): the link's minus WireGuard's overhead, at least 576."""
    return max(576, link_mtu_bytes - OVERHEAD_BYTES)


def choose_subnet(avoid: Sequence[str]) -> str:
    """The first candidate VPN subnet that overlaps none of *avoid* (CIDRs).

    Raises:
        FleetError: every candidate overlaps.
    """
    taken = [ipaddress.ip_network(a) for a in avoid]
    for candidate in _SUBNETS:
        net = ipaddress.ip_network(candidate)
        if not any(net.overlaps(t) for t in taken):
            return candidate
    raise FleetError(f"no VPN subnet free of the run's networks {list(avoid)}")


def _write_secret(path: Path, text: str) -> None:
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    path.chmod(0o600)


def _with_mtu(conf: str, mtu_bytes: int) -> str:
    """*conf* with ``MTU = mtu_bytes`` in its ``[Interface]`` (replacing one if present)."""
    conf = re.sub(r"(?m)^\s*MTU\s*=.*\n", "", conf)
    return re.sub(r"(?m)^\[Interface\]\n", f"[Interface]\nMTU = {mtu_bytes}\n", conf, count=1)


@dataclass
class Tunnel:
    """The WireGuard side of one run: fleet directory, container configs, their names.

    Args:
        work: The run's work directory (host side; mounted at *container_dir*).
        run_id: The run's id (part of interface names, at most 8 characters).
        mtu_bytes: The tunnel's MTU (both ends).
        container_dir: Where *work* is mounted in containers.
    """

    work: Path
    run_id: str
    mtu_bytes: int
    container_dir: str = "/e2e"
    server_vpn_ip: str = ""
    robot_vpn_ip: str = ""
    endpoint: str = ""
    _robots: int = field(default=0, repr=False)

    @property
    def fleet_dir(self) -> Path:
        """The fleet directory ``create_fleet`` made."""
        return self.work / "fleet"

    @property
    def conf_dir(self) -> Path:
        """Host directory of the configs containers read (0700, files 0600)."""
        return self.work / "wg"

    @property
    def server_iface(self) -> str:
        """The server's WireGuard interface (and config) name."""
        return f"fs-{self.run_id}"

    def create(self, avoid: Sequence[str]) -> None:
        """Make the fleet (server key, robot ``robot1``) and the server's container config.

        Args:
            avoid: CIDRs the VPN subnet must not overlap (the run's Docker networks).
        """
        shutil.rmtree(self.fleet_dir, ignore_errors=True)
        shutil.rmtree(self.conf_dir, ignore_errors=True)
        init = operations.create_fleet(
            self.fleet_dir, endpoint=f"{_PLACEHOLDER_HOST}:{WG_PORT}", name=f"e2e-{self.run_id}",
            subnet=choose_subnet(avoid), wireguard_port=WG_PORT)
        robot = operations.add_robot(self.fleet_dir, profiles.ROBOT, mtu_bytes=self.mtu_bytes)
        self.server_vpn_ip, self.robot_vpn_ip = str(init.fleet.server_ip), str(robot.robot.ip)
        conf = (self.fleet_dir / "server" / "wireguard" / "wg0.conf").read_text()
        _write_secret(self.conf_dir / f"{self.server_iface}.conf", _with_mtu(conf, self.mtu_bytes))

    def set_endpoint(self, server_host_ip: str) -> None:
        """Point the robot's ``Endpoint`` at the server container (fleet.yaml, then render)."""
        self.endpoint = f"{server_host_ip}:{WG_PORT}"
        fleet = replace(load_fleet(self.fleet_dir), endpoint=self.endpoint)
        plan = Plan()
        plan.write(fleet_file(self.fleet_dir), dump_fleet(fleet))
        plan.apply()
        operations.render_fleet(self.fleet_dir)

    def robot_iface(self) -> str:
        """A config for the next robot container; returns its interface name.

        Raises:
            FleetError: :meth:`set_endpoint` was not called.
        """
        if not self.endpoint:
            raise FleetError("the WireGuard endpoint is not set (start the server first)")
        self._robots += 1
        iface = f"fr-{self.run_id}-{self._robots}"
        conf = (self.fleet_dir / "robots" / profiles.ROBOT / "wireguard" / "wg0.conf")
        _write_secret(self.conf_dir / f"{iface}.conf", conf.read_text())
        return iface

    def container_env(self, iface: str) -> dict[str, str]:
        """Environment that makes the entrypoint bring *iface* up (or fail the container).

        The container starts as root; the entrypoint's ``setpriv`` drops to the ``fleetctl``
        user but keeps ``HOME=/root``, where rclpy cannot create its log directory: HOME is
        set to the fleetctl user's home.
        """
        return {"WG_CONFIG": f"{self.container_dir}/wg/{iface}.conf", "WG_REQUIRED": "1",
                "HOME": FLEETCTL_HOME}

    def server_url(self, port: int) -> str:
        """The server's WebSocket URL through the tunnel."""
        return f"ws://{self.server_vpn_ip}:{port}/"
