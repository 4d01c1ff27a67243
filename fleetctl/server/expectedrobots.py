"""The fleet's robots that have never connected, as the robot list shows them.

The registry knows a robot from its first message on. An operator who has just added a
robot (``fleetctl add-robot``, ``up``) and opens the page saw "0 robots" while ``fleetctl
status`` listed it: the relay's list now also carries the robots the auth map expects
and the registry has not seen. Which identities are robots is read from the map itself,
not from a naming convention: one matched by a single address (a robot's WireGuard /32
or /128) that may send its own ``/<name>/status``, which every robot reports on.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any

from fleetctl.server.authmap import AuthMap, Identity
from fleetctl.server.permissions import Permissions
from fleetctl.server.registry import RobotRecord, robot_name


def expected_robots(auth: AuthMap) -> tuple[str, ...]:
    """Names of the robots *auth* expects, sorted, each once."""
    return tuple(sorted({i.name for i in auth.identities if _is_robot(i)}))


def _is_robot(identity: Identity) -> bool:
    network = identity.network
    if network is None or network.num_addresses != 1:
        return False  # a token (a person, a tool) or a whole subnet: not one robot
    status = f"/{identity.name}/status"
    # A name that is not one topic segment ("ops team") cannot be a robot's.
    return robot_name(status) == identity.name and Permissions((identity,)).may_send(status)


def never_connected(name: str) -> dict[str, Any]:
    """The robot list's entry for a robot the registry has not seen: every field the
    registry's entries have (:meth:`RobotRegistry.as_json`), ``None`` where nothing is
    known yet."""
    unknown = dict.fromkeys(f.name for f in fields(RobotRecord))
    return {**unknown, "name": name, "online": False, "never_connected": True}
