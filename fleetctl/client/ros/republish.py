"""QoS of the publishers that republish fleet topics on the robot's ROS graph, and the
count of no_drop bursts deeper than their history.

A ROS ``KEEP_LAST`` writer overwrites a sample its readers have not acknowledged once
``depth`` newer ones are published; a sample a reader missed (a full shared-memory port,
a reader descheduled on a loaded robot) can then never be repaired. Fast DDS readers
acknowledge on the writer's heartbeat, about every 3 s (measured: a reliable writer's
``wait_for_all_acked`` returned after 2.0-2.8 s for 1 to 200 samples), so within that
time the depth is what bounds a burst. The relay delivers a
receiver's backlog of no_drop frames in one burst (a session flush after an outage, a
server restart): with depth 10, 200 events of 10 KB published at once to a listener
paused for 1 s arrived as 51 (Fast DDS's 0.5 MB shared-memory segment held the rest
until they were overwritten); with depth 1000, all 200.

So republishing writers are deep (:data:`DEEP_DEPTH`, the reading side's
``NO_DROP_DEPTH``) from their creation: a writer recreated on the first no_drop frame
would lose that burst to readers still matching it. A deep writer holds memory only
while a reader has not taken its samples (measured: 300 messages of 1 MB at 20 Hz to a
live reader: +1 MB of RSS; to a stopped reader: +286 MB), so a topic whose droppable
frames are large (a camera, a cloud: latest-only anyway) gets a shallow writer
(:data:`SHALLOW_DEPTH`) on its first such frame: at most :data:`DEEP_HISTORY_BYTES` of
big droppable messages are held for a stuck reader. KEEP_ALL is not used: a full
KEEP_ALL history blocks ``publish``, hence the link's thread, on a stuck reader.

A burst deeper than the history can still overwrite samples a slow reader never took;
rclpy does not say whether it did, so :class:`BurstWatch` counts the no_drop messages
published while ``depth`` others of the topic had been published within
:data:`ACK_WINDOW_S` (messages *at risk*), and the bridge says so once per topic.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

DEEP_DEPTH = 1000  # fleetctl.client.ros.qos.NO_DROP_DEPTH, the reading side's
SHALLOW_DEPTH = 10  # a droppable stream of big messages: latest-only anyway
# Bound of what a deep writer may hold of droppable messages for a stuck reader: a frame
# over DEEP_HISTORY_BYTES / DEEP_DEPTH (64 KiB) makes its topic's writer shallow.
DEEP_HISTORY_BYTES = 64 * 1024 * 1024
BIG_DROPPABLE_BYTES = DEEP_HISTORY_BYTES // DEEP_DEPTH
# Fast DDS's readers acknowledge on the writer's heartbeat (3 s by default): a writer
# frees no sample younger than this, so `depth` messages within it fill its history.
ACK_WINDOW_S = 3.0
# Topics whose recent publish times are kept (oldest forgotten): republished topics are
# bounded by the subscribe entries and their 64 dynamic publishers; ~32 KB each at depth 1000.
MAX_WATCHED_TOPICS = 256


def republish_qos(depth: int) -> QoSProfile:
    """Reliable, volatile, KEEP_LAST *depth* (as RViz's tools publish commands)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def depth_for(no_drop: bool, frame_bytes: int) -> int:
    """The history a topic's writer needs for a frame: deep, unless the frame is a
    droppable one over :data:`BIG_DROPPABLE_BYTES`."""
    if not no_drop and frame_bytes > BIG_DROPPABLE_BYTES:
        return SHALLOW_DEPTH
    return DEEP_DEPTH


class BurstWatch:
    """Counts no_drop messages published on a local topic while its writer's history
    was possibly full of unacknowledged samples (``depth`` published within
    :data:`ACK_WINDOW_S`): each may have overwritten one a slow reader had not taken.

    Args:
        clock: monotonic seconds (injected for tests).
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._recent: dict[str, deque[float]] = {}

    def published(self, topic: str, depth: int) -> bool:
        """Note one no_drop message published on *topic* by a writer of *depth*; True if
        it was published at risk (the *depth* before it all within the window)."""
        recent = self._recent.get(topic)
        if recent is None or recent.maxlen != depth:
            if len(self._recent) >= MAX_WATCHED_TOPICS:
                del self._recent[next(iter(self._recent))]
            recent = self._recent[topic] = deque(maxlen=depth)
        now = self._clock()
        at_risk = len(recent) == depth and now - recent[0] < ACK_WINDOW_S
        recent.append(now)
        return at_risk
