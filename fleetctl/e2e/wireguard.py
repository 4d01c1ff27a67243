"""Whether an e2e run uses WireGuard, the robot's tunnel MTU and the fleet subnet.

The fleet itself (keys, configs, the server container) is :mod:`fleetctl.e2e.deployment`'s:
``fleetctl up``'s own files. The image entrypoint (``images/entrypoint.sh``) brings
``wireguard-go`` up from ``WG_CONFIG`` (root, ``NET_ADMIN``, ``/dev/net/tun``), then drops to
the ``fleetctl`` user. Every container has its own filesystem, so each names its interface
``wg0`` as ``up``'s containers do (``wireguard-go``'s UAPI socket lives in ``/var/run``).

One robot identity (``robot1``, one key, one VPN address) serves every robot container of a
run: they run one after another, and each new container makes a fresh handshake from its own
address (WireGuard roaming).

MTU: the robot's is the link's minus 80 bytes (WireGuard's own rule: 40-byte IPv6 outer
header, 8 UDP, 32 WireGuard; ``add_robot --mtu``), so an encrypted packet is never fragmented
by the router and always fits the shaper's bucket. The server's is what ``up`` gives it (the
fleet's server config names none: the entrypoint's default, 1380).
"""

from __future__ import annotations

import ipaddress
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from fleetctl.deploy.compose import TUN_DEVICE, wireguard_wanted
from fleetctl.errors import FleetError

WG_PORT = 51820
OVERHEAD_BYTES = 80
# VPN subnets to try, first one that overlaps no Docker network of the run wins.
_SUBNETS = ("10.8.0.0/24", "10.88.0.0/24", "172.30.250.0/24", "192.168.250.0/24")


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
    if wireguard_wanted(requested, tun):
        return Mode(True, f"--wireguard {requested} and {tun} exists; wireguard-go in the "
                    "server and robot containers, robots reach the server through the tunnel")
    if requested == "off":
        return Mode(False, "--wireguard off; robots reach the server over the routed network")
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
