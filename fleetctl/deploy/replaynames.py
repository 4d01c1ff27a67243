"""The names a replay gives a recording's robots (``fleetctl replay``), and how ``fleetctl
status`` tells them from the fleet's robots.

Decision (docs/server.md, "Replaying onto live robots"): by default a replay sends every
recorded topic under a namespace no live robot has, ``/husky1/goal_pose`` as
``/husky1_replay/goal_pose``: a robot online never receives last week's goals, its
latched topics in the relay stay its own, and the page shows the replay as a robot of its
own (``husky1_replay``) with the same topic layout, so its views work unchanged.
"""

from __future__ import annotations

from fleetctl.deploy.yamlnodes import FleetInvalid

REPLAY_SUFFIX = "_replay"


def check_not_replay_name(name: str) -> None:
    """Refuse a new robot named like a replay (``dock_replay``): status and the page would
    mark it as a replay of ``dock``.

    Raises:
        FleetInvalid: *name* ends in :data:`REPLAY_SUFFIX` (the message says so).
    """
    if name.endswith(REPLAY_SUFFIX):
        raise FleetInvalid(("name",), f"robot name {name!r} ends in {REPLAY_SUFFIX}, "
                           "which `fleetctl replay` gives replayed robots (husky1 -> "
                           f"husky1{REPLAY_SUFFIX}): choose another name")


def replay_prefix(topic: str) -> str:
    """The renamed first segment of *topic*: ``/husky1/scan`` -> ``/husky1_replay``
    (``/tf`` -> ``/tf_replay``: a topic of one segment may be one robots subscribe to)."""
    first = topic[1:].partition("/")[0]
    return f"/{first}{REPLAY_SUFFIX}"


def recorded_prefix(topic: str) -> str:
    """The first segment of *topic*, as the prefix :func:`replay_prefix` renames."""
    return "/" + topic[1:].partition("/")[0]


def replayed_robot(name: str, fleet_robots: frozenset[str]) -> str | None:
    """The recorded robot a registry entry *name* replays (``husky1_replay`` ->
    ``husky1``), or ``None``: a robot of the fleet (*fleet_robots*) is never a replay,
    whatever its name."""
    if name in fleet_robots or not name.endswith(REPLAY_SUFFIX):
        return None
    return name[:-len(REPLAY_SUFFIX)] or None
