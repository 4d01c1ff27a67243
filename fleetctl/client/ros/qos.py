"""QoS of the client's local subscriptions, adapted to what the local publishers offer.

A best-effort reader matches every writer, but on a best-effort path DDS drops a whole
sample when one of its UDP fragments is late: measured here, a 1 MB PointCloud2 at 10 Hz
arrived at 5.6 Hz best-effort and at 10 Hz reliable, on one host. A reliable reader gets
every sample but does not match a best-effort writer at all. So, like rosbag2, each local
subscription follows its publishers: reliable when every discovered publisher is reliable,
best-effort as soon as one is not. Both use KEEP_LAST, so a slow client never blocks a
publisher.

Durability follows the same way (docs/client.md, "Latched topics"): a latched topic (Nav2's
``/map``, ``/tf_static``, ``/robot_description``) is published ``TRANSIENT_LOCAL``, usually
once and often before the client starts, and only a ``TRANSIENT_LOCAL`` reader is sent the
samples a writer published before the reader matched. But such a reader does not match a
``VOLATILE`` writer at all, so the subscription is ``TRANSIENT_LOCAL`` when every discovered
publisher offers it and ``VOLATILE`` otherwise. The switch recreates the reader, and the
publishers then send their stored samples to the new one: a map published before the
client, or before the client saw its publisher, is still received.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import get_rmw_implementation_identifier

from fleetctl.client.outagelog import LOG_EVERY, sampled
from fleetctl.client.ros.intake import LoopIntake, LoopServed, MessageCallback, TakesInfo
from fleetctl.client.seqgaps import SequenceGaps
from fleetctl.client.topichints import no_publisher_reason

log = logging.getLogger(__name__)

# A publish entry without any publisher this long is explained once (fleetctl.client.topichints).
NO_PUBLISHER_WARN_S = 30.0
SENSOR_DEPTH = 5  # droppable topics: the link keeps only the latest anyway
NO_DROP_DEPTH = 1000  # no_drop topics: absorb a burst until the link's FIFO takes it
# A latched writer usually keeps depth 1 (map_server, robot_state_publisher); DDS does not
# tell readers a writer's depth (rclpy reports it as 0), so the reader keeps the sensor
# depth: enough for the stored samples of a few publishers arriving at once on a match.
LATCHED_DEPTH = SENSOR_DEPTH
# Topics whose publishers are all TRANSIENT_LOCAL but which are streams, not a last state:
# rcl publishes every node's log on /rosout transient-local (depth 1000, lifespan 10 s) so
# that a late rqt_console sees recent lines. Marked latched, each log line replaced the map
# and the static TF in the relay's latched store as "the" state of /rosout, was kept and
# re-sent after each reconnect, and a transient-local reader was sent every node's last
# 1000 lines at each start and QoS switch. A volatile reader matches those writers too.
STREAM_TOPICS = frozenset({"/rosout"})
# A loop-served topic whose messages take longer than this (CPU of the loop's thread, in
# the callback: decode, encode, compress) holds the link's loop that long: pongs, ACKs and
# other topics' frames wait. After SLOW_MESSAGES_TO_MOVE such messages the topic is taken
# by the executor thread instead (the GIL is then handed over every 5 ms, not after the
# whole message). Measured (docs/benchmarks.md, "A realistic robot graph"): nav_msgs/Path
# of 2,000 poses 39 ms, MarkerArray of 300 line strips 84 ms; an Imu 0.05, a 921 KB Image 0.3.
SLOW_MESSAGE_S = 0.005
SLOW_MESSAGES_TO_MOVE = 3


def profile(reliable: bool, no_drop: bool, latched: bool = False) -> QoSProfile:
    """The subscription QoS for a topic (keep last).

    Args:
        reliable: RELIABLE, else BEST_EFFORT.
        no_drop: The topic is no_drop (deeper history).
        latched: TRANSIENT_LOCAL (receives what publishers stored before the match), else
            VOLATILE.
    """
    depth = NO_DROP_DEPTH if no_drop else (LATCHED_DEPTH if latched else SENSOR_DEPTH)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def publishers_reliable(infos: list[Any]) -> bool | None:
    """True if every publisher in *infos* (``get_publishers_info_by_topic``) is reliable;
    None if there are none."""
    if not infos:
        return None
    return all(info.qos_profile.reliability == ReliabilityPolicy.RELIABLE for info in infos)


def publishers_latched(infos: list[Any]) -> bool | None:
    """True if every publisher in *infos* offers TRANSIENT_LOCAL durability (a volatile
    one would not match a transient-local reader); None if there are none."""
    if not infos:
        return None
    return all(info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
               for info in infos)


def type_name(msg_type: Any) -> str:
    """``pkg/msg/Name`` of an rclpy message class (as publisher infos spell topic types)."""
    return f"{msg_type.__module__.split('.')[0]}/msg/{msg_type.__name__}"


class AdaptiveSubscription:
    """A raw subscription whose reliability and durability follow the topic's publishers.

    Starts reliable for no_drop topics (event publishers usually are) and best-effort for
    the others (matches any sensor driver at once), volatile for all; :meth:`refresh`,
    called periodically, switches when the discovered publishers say otherwise. A switch
    recreates the subscription, which may lose a message in flight: it happens only when
    the set of publishers changes. A switch to TRANSIENT_LOCAL makes the publishers send
    their stored samples again; one the volatile reader already got live (published
    between the publisher's discovery and the switch, within one refresh period) is then
    received twice, which a latched topic's receivers tolerate (they keep the last one).

    Args:
        node: the owning node.
        msg_type: the rclpy message class.
        topic: local topic.
        callback: receives raw CDR bytes and their publish time (wall clock ns; 0: not
            known).
        no_drop: the topic is no_drop (deeper history, reliable first).
        intake: Serve the subscription in the asyncio loop's thread (None: the executor
            serves it). If the intake cannot take it, the executor does, with a warning.
        on_lost: Called with the count of each gap in the publisher's sequence numbers:
            messages DDS lost before this client took them (:mod:`fleetctl.client.seqgaps`;
            also in :attr:`gaps`), after a WARNING (first and every 1000th gap).
    """

    def __init__(self, node: Node, msg_type: Any, topic: str,
                 callback: Callable[[bytes, int], None], *, no_drop: bool,
                 intake: LoopIntake | None = None,
                 on_lost: Callable[[int], None] | None = None) -> None:
        self.gaps = SequenceGaps()
        self._on_lost = on_lost
        self._unpublished_since_s: float | None = time.monotonic()  # None: has publishers
        self._said_unpublished = False
        self._node = node
        self._intake = intake
        self._msg_type = msg_type
        self._type_name = type_name(msg_type)
        self._warned_types: set[str] = set()
        self._topic = topic
        self._callback = callback
        self._no_drop = no_drop
        self.reliable = no_drop
        self.latched = False  # TRANSIENT_LOCAL: every publisher offers it
        self.switches = 0
        self.slow_messages = 0  # loop-served messages over SLOW_MESSAGE_S
        self._move_off_loop = False  # set on the loop's thread, acted on by refresh()
        self._slow_took_s = 0.0  # the message that decided it
        self._subscription = self._create()

    def _create(self) -> Any:
        intake = self._intake
        if intake is None or self.latched:
            # A latched topic's message (a map, a point-cloud map) comes once and may be
            # tens of MB: its deflate (0.45 s for a 16 MB float cloud, with the GIL
            # released) would stop the link's loop; on the executor it does not. The
            # intake is kept for when the topic is volatile again.
            return self._subscribe(TakesInfo(self._on_message))
        # The marker is set at creation, so the executor never serves this subscription.
        # Without rclpy's default QoS event handlers: the executor would wait on this
        # reader's status condition without taking its data, and on Fast DDS that wait
        # returns at once while data keeps arriving (the executor spun ~900 rounds/s).
        # What those handlers log (incompatible QoS or type) is covered by refresh():
        # the QoS follows the publishers, and other types are warned about there.
        subscription = self._subscribe(
            LoopServed(self._on_message),
            event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))
        try:
            intake.attach(subscription)
        except OSError as exc:
            log.warning("%s: taken by the executor thread (the loop cannot serve it: %s)",
                        self._topic, exc)
            self._intake = None
            self._node.destroy_subscription(subscription)
            return self._subscribe(TakesInfo(self._on_message))
        return subscription

    def _check_unpublished(self, published: bool) -> None:
        """Say once why a topic has had no publisher for :data:`NO_PUBLISHER_WARN_S` (it
        was silent for as long as the client ran), and when one appears after that."""
        now = time.monotonic()
        if published:
            if self._said_unpublished and self._unpublished_since_s is not None:
                log.info("%s: a publisher appeared after %.0f s", self._topic,
                         now - self._unpublished_since_s)
            self._unpublished_since_s = None
            return
        if self._unpublished_since_s is None:
            self._unpublished_since_s = now  # its publishers left: a new wait
            self._said_unpublished = False
        waited = now - self._unpublished_since_s
        if self._said_unpublished or waited < NO_PUBLISHER_WARN_S:
            return
        self._said_unpublished = True
        node = self._node
        published_topics = [(name, kinds) for name, kinds in node.get_topic_names_and_types()
                            if node.count_publishers(name) > 0]
        others = [n for n in node.get_node_names_and_namespaces() if n[0] != node.get_name()]
        log.warning("%s", no_publisher_reason(
            self._topic, self._type_name, waited, published_topics, len(others),
            node.context.get_domain_id(), get_rmw_implementation_identifier()))

    def _on_message(self, cdr: bytes, published_ns: int = 0, sequence: int = 0, /) -> None:
        if sequence and (lost := self.gaps.seen(sequence, self._publisher_count)):
            self._lost(lost)
        if not self.loop_served:
            self._callback(cdr, published_ns)
            return
        started = time.thread_time()
        self._callback(cdr, published_ns)
        took = time.thread_time() - started
        if took > SLOW_MESSAGE_S and not self._move_off_loop:
            self.slow_messages += 1
            if self.slow_messages >= SLOW_MESSAGES_TO_MOVE:
                self._move_off_loop = True
                self._slow_took_s = took

    def _publisher_count(self) -> int:
        return int(self._node.count_publishers(self._topic))

    def _lost(self, lost: int) -> None:
        if self._on_lost is not None:
            self._on_lost(lost)
        if not sampled(self.gaps.gaps):
            return
        if self.reliable:
            why = (f"it was published faster than this client took it, and DDS keeps only the "
                   f"last {profile(True, self._no_drop, self.latched).depth} messages here "
                   "(or the publisher's own KEEP_LAST history overwrote them)")
        else:
            why = ("best-effort messages DDS dropped: a large message one of whose UDP "
                   "fragments met a full receive buffer (docs/robot.md, 'Large messages'), "
                   "or a busy machine")
        log.warning("%s: %d %smessages published were lost before this client took them "
                    "(a gap in the publisher's sequence numbers; %d lost in %d gaps so far, "
                    "stats: lost_before_client; logged first and every %dth gap): %s",
                    self._topic, lost, "no_drop " if self._no_drop else "", self.gaps.lost,
                    self.gaps.gaps, LOG_EVERY, why)

    def _subscribe(self, callback: Callable[[bytes], None] | MessageCallback,
                   **options: Any) -> Any:
        return self._node.create_subscription(
            self._msg_type, self._topic, callback,
            profile(self.reliable, self._no_drop, self.latched), raw=True, **options,
        )

    def _warn_other_types(self, infos: list[Any]) -> None:
        for info in infos:
            other = info.topic_type
            if other != self._type_name and other not in self._warned_types:
                self._warned_types.add(other)
                log.warning("%s: a publisher sends %s, this client expects %s: its messages "
                            "are not received", self._topic, other, self._type_name)

    def _leave_loop(self) -> None:
        """Recreate the subscription served by the executor (on the executor's thread,
        like a QoS switch): its messages held the loop too long."""
        assert self._intake is not None
        self._intake.detach(self._subscription)
        self._node.destroy_subscription(self._subscription)
        self._intake = None
        self.gaps.restart()
        self._subscription = self._create()
        log.info("%s: its messages take %.0f ms each to convert (%d over %.0f ms), so the "
                 "executor thread takes them from now on, not the link's loop (which they "
                 "held that long); a rate_limit_hz on this entry saves that CPU too",
                 self._topic, 1000 * self._slow_took_s, self.slow_messages,
                 1000 * SLOW_MESSAGE_S)

    @property
    def loop_served(self) -> bool:
        """True when the asyncio loop's thread takes this topic's messages."""
        return self._intake is not None and not self.latched

    def refresh(self) -> None:
        """Match the reliability and durability of the publishers discovered so far (none:
        keep as is); hand a slow topic from the loop's thread to the executor's."""
        infos = self._node.get_publishers_info_by_topic(self._topic)
        self._warn_other_types(infos)
        self._check_unpublished(bool(infos))
        reliable = publishers_reliable(infos)
        latched = publishers_latched(infos)
        if self._topic in STREAM_TOPICS:
            latched = False if latched is not None else None
        if self._move_off_loop and self._intake is not None:
            self._leave_loop()
        if reliable is None or latched is None:
            return
        if (reliable, latched) == (self.reliable, self.latched):
            return
        if self._no_drop and not reliable and self.reliable:
            log.warning("no_drop topic %s has a best-effort publisher: messages can be lost "
                        "before the client sees them", self._topic)
        if self._intake is not None:
            self._intake.detach(self._subscription)
        self._node.destroy_subscription(self._subscription)
        self.reliable = reliable
        self.latched = latched
        self.switches += 1
        self.gaps.restart()
        self._subscription = self._create()
        log.info("%s: subscribed %s, %s to match its publishers", self._topic,
                 "reliable" if reliable else "best-effort",
                 "transient-local (latched)" if latched else "volatile")
