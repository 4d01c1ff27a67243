"""Why a ``publish`` topic has no publisher: the topics of the ROS graph it may have meant.

A publish entry whose topic nobody publishes was silent for as long as the client ran; the
usual causes in a robot's first week are a namespaced robot (the driver publishes
``/husky1/scan``, the entry says ``/scan``), a remapped or misspelt name (``/scan_raw``,
``/camera/color/image_raw`` against ``/camera/image_raw``), or another ROS domain or RMW,
where the client sees no topic of the robot at all. :func:`no_publisher_reason` words the
one line the client logs (:class:`fleetctl.client.ros.qos.AdaptiveSubscription`, after
:data:`~fleetctl.client.ros.qos.NO_PUBLISHER_WARN_S`). Pure: the graph is a list of
``(topic, types)`` as rclpy's ``get_topic_names_and_types`` gives it.
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence

MAX_CANDIDATES = 3


def candidates(topic: str, type_name: str,
               graph: Sequence[tuple[str, Sequence[str]]]) -> list[str]:
    """Topics of *graph* that *topic* may have meant, best first: those ending in its
    name (a namespace in front) and those whose name is close, preferring *type_name*."""
    others = [(name, list(types)) for name, types in graph if name != topic]
    ending = [name for name, _ in others if name.endswith(topic)]
    close = difflib.get_close_matches(topic, [name for name, _ in others], n=MAX_CANDIDATES,
                                      cutoff=0.6)
    ordered = list(dict.fromkeys([*ending, *close]))
    of_type = {name for name, types in others if type_name in types}
    ordered.sort(key=lambda name: name not in of_type)  # stable: same type first
    return ordered[:MAX_CANDIDATES]


def no_publisher_reason(topic: str, type_name: str, waited_s: float,
                        graph: Sequence[tuple[str, Sequence[str]]], other_nodes: int,
                        domain_id: int, rmw: str) -> str:
    """The line that says why *topic* has had no publisher for *waited_s* seconds.

    Args:
        graph: The published topics and their types (the client's own subscriptions,
            which have no publisher, left out).
        other_nodes: How many nodes besides the client's the graph shows.
    """
    head = f"{topic}: no publisher in {waited_s:.0f} s, so nothing of it is sent"
    if other_nodes == 0:
        return (f"{head}, and the client sees no other node at all: are the robot's nodes "
                f"in ROS_DOMAIN_ID={domain_id} with {rmw} (and the same "
                "ROS_AUTOMATIC_DISCOVERY_RANGE / ROS_LOCALHOST_ONLY)?")
    types = {name: list(kinds) for name, kinds in graph}
    found = candidates(topic, type_name, graph)
    if found:
        named = ", ".join(f"{name} ({', '.join(types[name])})" for name in found)
        return (f"{head}; the ROS graph has {named}: a namespaced or remapped driver? set "
                f"this entry's topic to the one it publishes")
    same_type = sorted(name for name, kinds in graph if type_name in kinds and name != topic)
    if same_type:
        return (f"{head}; {type_name} is published on {', '.join(same_type[:MAX_CANDIDATES])}"
                ": set this entry's topic to the one it should send")
    return f"{head}; is its driver running?"
