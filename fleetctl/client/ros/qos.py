"""QoS of the client's local subscriptions, adapted to what the local publishers offer.

A best-effort reader matches every writer, but on a best-effort path DDS drops a whole
sample when one of its UDP fragments is late: measured here, a 1 MB PointCloud2 at 10 Hz
arrived at 5.6 Hz best-effort and at 10 Hz reliable, on one host. A reliable reader gets
every sample but does not match a best-effort writer at all. So, like rosbag2, each local
subscription follows its publishers: reliable when every discovered publisher is reliable,
best-effort as soon as one is not. Both use KEEP_LAST, so a slow client never blocks a
publisher.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

log = logging.getLogger(__name__)

SENSOR_DEPTH = 5  # droppable topics: the link keeps only the latest anyway
NO_DROP_DEPTH = 1000  # no_drop topics: absorb a burst until the link's FIFO takes it


def profile(reliable: bool, no_drop: bool) -> QoSProfile:
    """The subscription QoS for a topic (volatile, keep last)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=NO_DROP_DEPTH if no_drop else SENSOR_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
    )


def publishers_reliable(node: Node, topic: str) -> bool | None:
    """True if every discovered publisher of *topic* is reliable; None if there are none."""
    infos = node.get_publishers_info_by_topic(topic)
    if not infos:
        return None
    return all(info.qos_profile.reliability == ReliabilityPolicy.RELIABLE for info in infos)


class AdaptiveSubscription:
    """A raw subscription whose reliability follows the topic's publishers.

    Starts reliable for no_drop topics (event publishers usually are) and best-effort for
    the others (matches any sensor driver at once); :meth:`refresh`, called periodically,
    switches when the discovered publishers say otherwise. A switch recreates the
    subscription, which may lose a message in flight: it happens only when the set of
    publishers changes.

    Args:
        node: the owning node.
        msg_type: the rclpy message class.
        topic: local topic.
        callback: receives raw CDR bytes.
        no_drop: the topic is no_drop (deeper history, reliable first).
    """

    def __init__(self, node: Node, msg_type: Any, topic: str,
                 callback: Callable[[bytes], None], *, no_drop: bool) -> None:
        self._node = node
        self._msg_type = msg_type
        self._topic = topic
        self._callback = callback
        self._no_drop = no_drop
        self.reliable = no_drop
        self.switches = 0
        self._subscription = self._create()

    def _create(self) -> Any:
        return self._node.create_subscription(
            self._msg_type, self._topic, self._callback,
            profile(self.reliable, self._no_drop), raw=True,
        )

    def refresh(self) -> None:
        """Match the reliability of the publishers discovered so far (none: keep as is)."""
        wanted = publishers_reliable(self._node, self._topic)
        if wanted is None or wanted == self.reliable:
            return
        if self._no_drop and not wanted:
            log.warning("no_drop topic %s has a best-effort publisher: messages can be lost "
                        "before the client sees them", self._topic)
        self._node.destroy_subscription(self._subscription)
        self.reliable = wanted
        self.switches += 1
        self._subscription = self._create()
        log.info("%s: subscribed %s to match its publishers", self._topic,
                 "reliable" if wanted else "best-effort")
