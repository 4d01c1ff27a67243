"""Whether a recorded channel is latched, from what the recording stores.

The writer (:mod:`fleetctl.server.recording.mcapfile`) gives a latched topic (a frame
with the latched flag: a map, ``/tf_static``) rosbag2's ``offered_qos_profiles`` with
``durability: transient_local``, and other topics ``volatile``; ``ros2 bag record``
writes the same key. Reading it back is the only way to tell a latched channel of a
closed file (the frames' flag is not stored per message).
"""

from __future__ import annotations

from collections.abc import Mapping

import yaml

# rosbag2 before Iron wrote the durability enum's number: 1 is transient_local.
_TRANSIENT_LOCAL = ("transient_local", 1)


def is_latched(metadata: Mapping[str, str]) -> bool:
    """Whether a channel's ``offered_qos_profiles`` say ``transient_local``; ``False``
    without them, or when they are not YAML (a foreign file: recorded as volatile)."""
    try:
        profiles = yaml.safe_load(metadata.get("offered_qos_profiles", "") or "[]")
    except yaml.YAMLError:
        return False
    if not isinstance(profiles, list):
        return False
    return any(isinstance(p, dict) and p.get("durability") in _TRANSIENT_LOCAL
               for p in profiles)
