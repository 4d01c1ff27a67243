"""The robot client's ROS 2 side: local topics in, fleet frames out, and back.

:class:`Bridge` is an rclpy node. For every ``publish`` entry of the client config it holds a
*raw* subscription (CDR bytes, no Python message object is ever built by rclpy) whose
reliability follows the topic's publishers (:mod:`fleetctl.client.ros.qos`) and, in the
callback, asks the link whether the topic is due (Robofleet Algorithm 1's rate limit) before
doing any work, then converts CDR -> rosbags message -> FlatBuffer frame, compresses it when
the entry asks for it (:mod:`fleetctl.wire.compression`; the link fragments afterwards) and
hands the frame to the link. For every ``subscribe`` entry it holds a publisher; frames from
the link (reassembled and decompressed by the link) are decoded, serialized to CDR and
published as bytes. Those publishers keep a deep history (:mod:`fleetctl.client.ros.republish`)
so that a backlog of no_drop frames the relay delivers at once reaches slow local readers.

Latched topics (docs/client.md): a subscription whose publishers all offer TRANSIENT_LOCAL
marks its frames ``latched``; one over :data:`LATCHED_COMPRESS_BYTES` is deflate-compressed
when the entry's compression is ``none`` (the page decodes deflate), and the last one of
each topic is kept and re-sent by :meth:`Bridge.resend_latched` on a new connection. A
received latched frame switches its local topic's publisher to TRANSIENT_LOCAL for good,
so nodes started later on this robot still get the map.

The node knows nothing about WebSockets: it talks to the link through two callables
(:class:`LinkPort`) so it is tested without a server, and the link is tested without ROS.
Callbacks run on the rclpy executor thread, except those of uncompressed ``publish`` topics
when the node is given a :class:`~fleetctl.client.ros.intake.LoopIntake` (then on the asyncio
thread); :meth:`Bridge.deliver` is called from the asyncio thread (rclpy publishers may be
used from any thread).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, cast

import re2
from rclpy.exceptions import InvalidTopicNameException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

from fleetctl.client.config import ClientConfig, PublishSpec, SubscribeSpec
from fleetctl.client.latched import LatchedFrames
from fleetctl.client.outagelog import LOG_EVERY, sampled
from fleetctl.client.ros import qos
from fleetctl.client.ros.ddsbuffers import LargeMessageCheck
from fleetctl.client.ros.executor import steady_timer
from fleetctl.client.ros.intake import LoopIntake
from fleetctl.client.ros.msgtypes import message_class
from fleetctl.client.ros.qos import AdaptiveSubscription
from fleetctl.client.ros.republish import (
    ACK_WINDOW_S,
    DEEP_DEPTH,
    SHALLOW_DEPTH,
    BurstWatch,
    depth_for,
    republish_qos,
)
from fleetctl.client.ros.tfsource import TfRepublisher, start_tf
from fleetctl.client.ros.videotopic import VideoTopic, video_topics
from fleetctl.client.transport import LinkFeedback
from fleetctl.client.video import KEYFRAME_REQUEST_TYPE
from fleetctl.client.viewercloud import VIEWER_CLOUD_TYPE, ViewerClouds
from fleetctl.errors import ConfigError
from fleetctl.wire.compression import LATCHED_DEFLATE_LEVEL, CompressionCodec, compress

log = logging.getLogger(__name__)
BATTERY_TYPE = "sensor_msgs/msg/BatteryState"

# Topics republished locally (goal poses, events, scans): reliable, like RViz's tools
# publish commands; the depth is fleetctl.client.ros.republish's (deep; shallow for big
# droppable messages). COMMAND_QOS is the shallow one.
COMMAND_QOS = republish_qos(SHALLOW_DEPTH)
# A received latched topic republished locally: late joiners get the last message, like
# from map_server itself (depth 1, as map_server and robot_state_publisher keep).
LATCHED_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# Latched messages above this go deflate-compressed when the entry says none: maps (an
# occupancy grid compresses ~50x) are what is big and latched; deflate because the page
# decodes it natively (DecompressionStream), unlike zstd.
LATCHED_COMPRESS_BYTES = 64 * 1024
QOS_REFRESH_PERIOD_S = 1.0  # how often local subscriptions re-check their publishers' QoS
MAX_DYNAMIC_PUBLISHERS = 64  # regex subscriptions without local_topic: one publisher per topic
# Remote topics a regex entry cannot republish under their own name (not a ROS 2 name: the
# relay allows '-' and '~', ROS 2 neither; a token starting with a digit; over 247
# characters), remembered so that a 30 Hz topic is not refused by rcl 30 times a second.
MAX_REFUSED_NAMES = 256


@dataclass(frozen=True)
class LinkPort:
    """What the node needs from the link.

    Attributes:
        admit: ``admit(remote_topic) -> bool``: False when the topic's rate limit says skip
            this message (checked before any decoding work).
        send: ``send(spec, frame, published_ns)``: queue an encoded frame of publish
            entry *spec*, published at *published_ns* (wall clock; 0: not known)
            (thread-safe; called from the rclpy executor's thread or the loop's).
        send_status: ``send_status(frame)``: queue an encoded RobofleetStatus frame.
        connects: ``connects() -> int``: connections the link has established so far
            (read from any thread); when it grows, the kept latched frames are offered
            again (:meth:`Bridge.resend_latched`). None: never re-sent.
        send_video: ``send_video(spec, frame, keyframe)``: like *send*, for a video frame
            (a keyframe is never dropped for the frames after it); None: *send*.
        feedback: ``feedback(remote_topic)``: the link's rate and the topic's drops, for
            the video bitrate and keyframes (any thread); None: video does not adapt.
    """

    admit: Callable[[str], bool]
    send: Callable[[PublishSpec, bytes, int], None]
    send_status: Callable[[bytes], None]
    connects: Callable[[], int] | None = None
    send_video: Callable[[PublishSpec, bytes, bool], None] | None = None
    feedback: Callable[[str], LinkFeedback] | None = None


@dataclass
class BridgeStats:
    """Counters of the node (read from any thread; each is a plain int).

    Attributes:
        local_in: raw messages received from local topics.
        rate_limited: of those, skipped because the link said not yet.
        sent: frames handed to the link.
        compressed: of those, sent as a Compressed frame.
        compression_skipped: of those, sent plain on a compressed topic because
            compression would not have saved 5 % (incompressible data).
        encode_errors: local messages that could not be decoded, encoded or compressed
            (logged, first and every 1000th per topic); ``per_topic_encode_errors`` by
            local topic.
        frames_in: frames received from the link.
        published_local: of those, published on a local topic.
        decode_errors: frames that could not be decoded or serialized (logged).
        type_mismatch: frames whose type differs from the subscribe entry's (dropped).
        unmatched: frames matching no subscribe entry (dropped).
        publishers_over_limit: frames dropped because a regex entry already has
            :data:`MAX_DYNAMIC_PUBLISHERS` local topics.
        bad_local_topic: frames dropped because their topic, which a regex entry without
            ``local_topic`` republishes as it is, is not a valid ROS 2 topic name
            (logged first and every 1000th per topic, with rcl's reason).
        status_sent: RobofleetStatus frames sent.
        latched_sent: of ``sent``, frames marked latched (TRANSIENT_LOCAL publishers).
        latched_compressed: of those, deflate-compressed because they were large.
        latched_resent: kept latched frames offered again on a new connection.
        latched_republished: of ``published_local``, latched frames (TRANSIENT_LOCAL).
        lost_before_client: local messages DDS lost before the node took them (gaps in
            their publisher's sequence numbers, :mod:`fleetctl.client.seqgaps`), never in
            ``local_in``; ``per_topic_lost`` by local topic.
        no_drop_at_risk: of ``published_local``, no_drop messages republished while the
            publisher's history (``republish.DEEP_DEPTH``) may have been full of samples
            a local reader had not acknowledged: each may have overwritten one a slow
            reader never took (:class:`~fleetctl.client.ros.republish.BurstWatch`; one
            WARNING per topic); ``per_topic_at_risk`` by remote topic (bounded).
    """

    local_in: int = 0
    rate_limited: int = 0
    sent: int = 0
    compressed: int = 0
    compression_skipped: int = 0
    encode_errors: int = 0
    frames_in: int = 0
    published_local: int = 0
    decode_errors: int = 0
    type_mismatch: int = 0
    unmatched: int = 0
    publishers_over_limit: int = 0
    bad_local_topic: int = 0
    status_sent: int = 0
    latched_sent: int = 0
    latched_compressed: int = 0
    latched_resent: int = 0
    latched_republished: int = 0
    lost_before_client: int = 0
    no_drop_at_risk: int = 0
    per_topic_at_risk: dict[str, int] = field(default_factory=dict)
    per_topic_sent: dict[str, int] = field(default_factory=dict)
    per_topic_lost: dict[str, int] = field(default_factory=dict)
    per_topic_encode_errors: dict[str, int] = field(default_factory=dict)


def _entry_class(where: str, type_name: str) -> Any:
    """The message class of a config entry; fails at start (not on the first message).

    Raises:
        ConfigError: naming the entry, when the type's package is not installed.
    """
    try:
        return message_class(type_name)
    except ConfigError as exc:
        raise ConfigError(f"{where}: type: {exc}") from exc


class BadLocalTopic(Exception):
    """A remote topic cannot be republished under its own name: rcl refuses the name."""


class _Route:
    """One subscribe entry: its matcher and its local publisher(s)."""

    def __init__(self, node: Node, spec: SubscribeSpec) -> None:
        self.spec = spec
        self._node = node
        self._cls = message_class(spec.type)
        self._regex = re2.compile(spec.remote_topic) if spec.is_regex else None
        self._publishers: dict[str, Any] = {}
        self._latched: set[str] = set()  # local topics whose publisher is TRANSIENT_LOCAL
        # Depth of each volatile publisher (fleetctl.client.ros.republish): deep from the
        # start, so the first no_drop burst finds it matched and deep.
        self.depths: dict[str, int] = {}
        self.refused: dict[str, str] = {}  # local topic -> rcl's reason (bounded)
        if spec.local_topic is not None:
            self._publishers[spec.local_topic] = node.create_publisher(
                self._cls, spec.local_topic, republish_qos(DEEP_DEPTH)
            )
            self.depths[spec.local_topic] = DEEP_DEPTH

    def matches(self, topic: str) -> bool:
        if self._regex is None:
            return topic == self.spec.remote_topic
        return self._regex.fullmatch(topic) is not None

    def publisher_for(self, topic: str, latched: bool = False, *, no_drop: bool = False,
                      frame_bytes: int = 0) -> Any | None:
        """The publisher for remote *topic*; None when the dynamic bound is reached.

        Raises:
            BadLocalTopic: *topic* is republished under its own name (a regex entry
                without ``local_topic``) and that is not a ROS 2 topic name.

        The first *latched* frame of a local topic replaces its volatile publisher with a
        TRANSIENT_LOCAL one for good (it also serves volatile subscribers). One publisher
        per topic rather than a second, latched one beside it: subscribers that follow
        their publishers' QoS (rosbag2, a fleetctl client) see a single durability, and a
        late joiner never gets an older latched message than the last one. A volatile
        subscriber that had matched the old publisher may miss this first latched
        message while it discovers the new one; latched topics' readers (RViz's map
        display, Nav2's static layer, tf2) are TRANSIENT_LOCAL and do not.

        A volatile publisher is deep (:mod:`fleetctl.client.ros.republish`); the first
        droppable frame over ``BIG_DROPPABLE_BYTES`` (*frame_bytes*, *no_drop*) replaces it
        by a shallow one for good, which bounds what a stuck reader makes it hold.
        """
        local = self.spec.local_topic or topic
        publisher = self._publishers.get(local)
        depth = depth_for(no_drop, frame_bytes)
        if publisher is not None and local not in self._latched and (
                latched or depth < self.depths.get(local, DEEP_DEPTH)):
            self._node.destroy_publisher(publisher)
            del self._publishers[local]
            publisher = None
        if publisher is None:
            if local in self.refused:
                raise BadLocalTopic(self.refused[local])
            if len(self._publishers) >= MAX_DYNAMIC_PUBLISHERS:
                return None
            if latched or local in self._latched:
                qos_profile = LATCHED_QOS
            else:
                depth = min(depth, self.depths.get(local, DEEP_DEPTH))  # shallow for good
                qos_profile = republish_qos(depth)
            try:
                publisher = self._node.create_publisher(self._cls, local, qos_profile)
            except InvalidTopicNameException as exc:
                reason = (str(exc).split("\n", 1)[0].removeprefix("Invalid topic name: ")
                          .rstrip(":").replace("'255U - 8U'", "247 characters"))
                if len(self.refused) < MAX_REFUSED_NAMES:
                    self.refused[local] = reason
                raise BadLocalTopic(reason) from None
            if latched:
                self._latched.add(local)
            else:
                self.depths[local] = depth
            self._publishers[local] = publisher
        return publisher

    def depth_of(self, topic: str) -> int:
        """History depth of remote *topic*'s volatile publisher (0: latched, none yet)."""
        local = self.spec.local_topic or topic
        return 0 if local in self._latched else self.depths.get(local, 0)


def _failure_hint(exc: BaseException) -> str:
    """What a robot team should know about a message that failed: a string field that is
    not UTF-8 is the publisher's to fix (ROS 2 strings are UTF-8; rclcpp sends any bytes)."""
    cause = exc.__cause__ or exc.__context__
    if isinstance(exc, UnicodeDecodeError) or isinstance(cause, UnicodeDecodeError):
        return ("; a string field is not UTF-8 (ROS 2 strings are UTF-8 text): the publisher "
                "sends other bytes, e.g. a latin-1 degree sign")
    return ""


def _check_no_echo(config: ClientConfig) -> None:
    """Refuse a subscribe entry republishing onto a topic the client also sends.

    The node would pick up its own republished messages and send them again, forever.

    Raises:
        ConfigError: naming both entries.
    """
    sent = {spec.topic: f"publish[{i}]" for i, spec in enumerate(config.publish)}
    if config.tf is not None:
        sent.update({"/tf": "the tf section", "/tf_static": "the tf section"})
    for j, sub in enumerate(config.subscribe):
        if sub.local_topic is not None and sub.local_topic in sent:
            raise ConfigError(
                f"subscribe[{j}] ({sub.remote_topic}): local_topic: {sub.local_topic} is also "
                f"sent by {sent[sub.local_topic]}: the client would echo it forever"
            )


class Bridge(Node):
    """The client's rclpy node (see the module docstring).

    Args:
        config: the validated client config.
        codec: a :class:`fleetctl.wire.codec.Codec` (``encode``/``decode``).
        typestore: the rosbags type store of the codec's registry (CDR conversions).
        port: the link's side of the bridge.
        encode_status: ``encode_status(battery_level) -> bytes`` building this robot's
            RobofleetStatus frame; battery is a fraction in [0, 1] or None when unknown.
        clock_ns: wall clock in ns since the epoch (injected for tests).
        context: the rclpy context of the node (None: the global one).
        intake: takes the uncompressed ``publish`` topics' messages in the asyncio loop's
            thread (None: the executor does).
    """

    def __init__(
        self,
        config: ClientConfig,
        codec: Any,
        typestore: Any,
        port: LinkPort,
        encode_status: Callable[[float | None], bytes],
        clock_ns: Callable[[], int] = time.time_ns,
        context: Any = None,
        intake: LoopIntake | None = None,
    ) -> None:
        _check_no_echo(config)
        # No services: the node's settings come from the client's YAML file, and its
        # executor (fleetctl.client.ros.executor) serves topics and timers only.
        super().__init__(
            f"fleetctl_client_{config.robot_name}", context=context,
            start_parameter_services=False,
            parameter_overrides=[Parameter("start_type_description_service", value=False)])
        self.stats = BridgeStats()
        self._mismatches: dict[tuple[str, str], int] = {}  # (topic, type) -> frames dropped
        self._refused_frames: dict[str, int] = {}  # remote topic -> frames (bounded)
        self._said_too_large: set[str] = set()  # latched topics over the kept bound, said
        self._bursts = BurstWatch()  # no_drop messages republished beyond the history
        self._config = config
        self._codec = codec
        self._typestore = typestore
        self._port = port
        self._encode_status = encode_status
        self._clock_ns = clock_ns
        self._seq: dict[str, int] = {}
        self._seq_lock = threading.Lock()  # callbacks run on the executor's and the loop's thread
        self._battery: float | None = None
        self._battery_warned: set[str] = set()  # other types on the battery topic, said
        self.inputs: list[AdaptiveSubscription] = []
        self.latched = LatchedFrames[PublishSpec]()
        # <remote_topic>/viewer beside clouds with viewer_cloud: (fleetctl.client.viewercloud)
        self.viewer_clouds = ViewerClouds(
            self.send_message, codec.registry.get(VIEWER_CLOUD_TYPE).cls)
        self._connects_seen = 0
        self.large_messages = LargeMessageCheck()
        for i, spec in enumerate(config.publish):
            cls = _entry_class(f"publish[{i}] ({spec.topic})", spec.type)
            self.inputs.append(AdaptiveSubscription(
                self, cls, spec.topic, self._make_callback(spec), no_drop=spec.no_drop,
                # A compressed topic's zstd/deflate work (milliseconds per megabyte, with
                # the GIL released) stays off the loop, which other topics' frames wait on.
                intake=intake if spec.compression == "none" else None,
                on_lost=self._lost_counter(spec.topic)))
        steady_timer(self, QOS_REFRESH_PERIOD_S, self._refresh_qos)
        self.tf: TfRepublisher | None = None
        if config.tf is not None:
            self.tf = start_tf(self, config.tf, config.robot_name, typestore, self.send_message)
        self._routes: list[_Route] = []
        for i, sub in enumerate(config.subscribe):
            _entry_class(f"subscribe[{i}] ({sub.remote_topic})", sub.type)
            self._routes.append(_Route(self, sub))
        if config.status.battery_topic is not None:
            from sensor_msgs.msg import BatteryState

            self.create_subscription(
                BatteryState, config.status.battery_topic, self._on_battery,
                qos.profile(reliable=False, no_drop=False),
            )
        steady_timer(self, config.status.period_s, self.send_status)
        # Camera entries with video: (fleetctl.client.ros.videotopic), by remote topic.
        self.videos: dict[str, VideoTopic] = video_topics(
            config.publish, typestore=typestore, codec=codec, send=self._send_video,
            relay=self.send_message, next_seq=self._next_seq, feedback=port.feedback)

    # --- local -> fleet -----------------------------------------------------------------

    def _refresh_qos(self) -> None:
        for subscription in self.inputs:
            subscription.refresh()
        self._check_reconnect()

    def _check_reconnect(self) -> None:
        """Re-send the kept latched frames once per new connection (checked every
        :data:`QOS_REFRESH_PERIOD_S`). The first connection sends what was queued anyway."""
        if self._port.connects is None:
            return
        connects = self._port.connects()
        if connects > self._connects_seen:
            if self._connects_seen > 0:
                self.resend_latched()
                if self.tf is not None:
                    self.tf.reconnected()
            self._connects_seen = connects

    def _lost_counter(self, topic: str) -> Callable[[int], None]:
        def lost(count: int) -> None:
            self.stats.lost_before_client += count
            self.stats.per_topic_lost[topic] = self.stats.per_topic_lost.get(topic, 0) + count

        return lost

    def _make_callback(self, spec: PublishSpec) -> Callable[[bytes, int], None]:
        index = len(self.inputs)  # the AdaptiveSubscription this callback is given to

        def callback(cdr: bytes, published_ns: int = 0, /) -> None:
            self.on_local_message(spec, cdr, latched=self.inputs[index].latched,
                                  published_ns=published_ns)

        return callback

    def on_local_message(self, spec: PublishSpec, cdr: bytes, *, latched: bool = False,
                         published_ns: int = 0) -> None:
        """Encode one local CDR message of *spec* and hand it to the link (unless rate limited).

        *latched*: the topic's publishers are TRANSIENT_LOCAL (the frame is marked so).
        *published_ns*: its source timestamp (0: not known), for the link.
        """
        self.stats.local_in += 1
        self.large_messages.seen(spec.topic, len(cdr))
        if not self._port.admit(spec.remote_topic):
            self.stats.rate_limited += 1
            return
        if spec.video is not None and self.videos[spec.remote_topic].offer(cdr):
            return  # encoded on the topic's own thread, sent by _send_video
        try:
            # A view: rosbags slices off the CDR header, which copies a bytes object
            # (1 MB per cloud) but not a view; arrays then reference rclpy's buffer.
            msg = self._typestore.deserialize_cdr(memoryview(cdr), spec.type)
        except Exception as exc:  # a bad local message must never stop the node
            self._local_failure(spec, "decode", exc)
            return
        self.send_message(spec, msg, latched=latched, published_ns=published_ns)
        if spec.viewer_cloud is not None:  # after the full cloud, which is sent regardless
            self.viewer_clouds.on_cloud(spec, msg, latched=latched)

    def send_message(self, spec: PublishSpec, msg: Any, *, latched: bool = False,
                     published_ns: int = 0) -> bool:
        """Encode a message object (rosbags, of ``spec.type``) and hand it to the link.

        Compression as the entry says, or deflate for a large latched message; a latched
        frame is also kept for :meth:`resend_latched`. Thread-safe.

        Returns:
            False when it could not be encoded (counted in ``encode_errors`` and logged).
        """
        try:
            # A view, not a copy: the link only reads it (fragments are new buffers).
            frame = self._codec.encode_view(
                msg,
                spec.type,
                spec.remote_topic,
                no_drop=spec.no_drop,
                publish_time_ns=self._clock_ns(),
                seq=self._next_seq(spec.remote_topic),
                latched=latched,
            )
            if spec.compression != "none":
                frame = self._compress(spec, frame)
            elif latched and len(frame) > LATCHED_COMPRESS_BYTES:
                frame = self._compress_latched(spec, frame)
        except Exception as exc:  # a bad local message must never stop the node
            self._local_failure(spec, "encode", exc)
            return False
        self._keep_latched(spec, frame, latched)
        self._port.send(spec, frame, published_ns)
        self.stats.sent += 1
        self.stats.per_topic_sent[spec.remote_topic] = (
            self.stats.per_topic_sent.get(spec.remote_topic, 0) + 1
        )
        return True

    def _local_failure(self, spec: PublishSpec, what: str, exc: Exception) -> None:
        """Count a local message of *spec* that could not be decoded or encoded; log the
        first and every 1000th of its topic (it was a WARNING per message: a driver
        sending a latin-1 degree sign at 20 Hz wrote 20 lines a second)."""
        self.stats.encode_errors += 1
        seen = self.stats.per_topic_encode_errors.get(spec.topic, 0) + 1
        self.stats.per_topic_encode_errors[spec.topic] = seen
        if sampled(seen):
            log.warning("cannot %s %s from %s, dropped (%d so far; logged first and every "
                        "%dth): %s%s", what, spec.type, spec.topic, seen, LOG_EVERY, exc,
                        _failure_hint(exc))

    def _compress(self, spec: PublishSpec, frame: bytes) -> bytes:
        """Before the link fragments it: receivers reassemble, then decompress."""
        out = compress(frame, codec=CompressionCodec.from_name(spec.compression),
                       topic=spec.remote_topic, no_drop=spec.no_drop, frame_codec=self._codec)
        if out is frame:
            self.stats.compression_skipped += 1
        else:
            self.stats.compressed += 1
        return out

    def _compress_latched(self, spec: PublishSpec, frame: bytes) -> bytes:
        out = compress(frame, codec=CompressionCodec.DEFLATE, topic=spec.remote_topic,
                       no_drop=spec.no_drop, frame_codec=self._codec,
                       level=LATCHED_DEFLATE_LEVEL)
        if out is not frame:
            self.stats.latched_compressed += 1
        return out

    def _keep_latched(self, spec: PublishSpec, frame: bytes, latched: bool) -> None:
        if latched:
            self.stats.latched_sent += 1
            too_large = self.latched.stats.too_large
            self.latched.put(spec.remote_topic, spec, frame)
            if self.latched.stats.too_large > too_large:
                self._latched_too_large(spec, len(frame))
        elif spec.remote_topic in self.latched:
            # The topic's last message is no longer latched: re-sending the old one would
            # bring back stale data after a reconnect.
            self.latched.forget(spec.remote_topic)

    def _latched_too_large(self, spec: PublishSpec, size: int) -> None:
        """Say once per topic that a latched message is too big to be kept (a point-cloud
        map): it was counted in ``latched.stats.too_large`` and nothing else said so."""
        if spec.topic in self._said_too_large:
            return
        self._said_too_large.add(spec.topic)  # bounded: topics of the config's entries
        log.warning(
            "%s: a latched message of %d bytes as sent (compressed when that saved 5 %%) is "
            "over the %d bytes this client keeps to send again after a reconnect, and the "
            "relay keeps latched messages of at most latched_message_bytes (16 MiB by "
            "default) for viewers and robots who come later: they may never get it; "
            "publish it smaller (a coarser grid, a downsampled cloud)", spec.topic, size,
            self.latched.max_bytes)

    def resend_latched(self) -> int:
        """Offer the kept latched frames again (call on a new connection to the server).

        Returns:
            How many frames were offered.
        """
        frames = self.latched.snapshot()
        for _, spec, frame in frames:
            # A kept frame may be the encoder's read-only view; the link only reads it.
            self._port.send(spec, cast(bytes, frame), 0)
        self.stats.latched_resent += len(frames)
        return len(frames)

    def _send_video(self, spec: PublishSpec, frame: bytes, keyframe: bool) -> None:
        if self._port.send_video is None:
            self._port.send(spec, frame, 0)
        else:
            self._port.send_video(spec, frame, keyframe)
        self.stats.sent += 1
        self.stats.per_topic_sent[spec.remote_topic] = (
            self.stats.per_topic_sent.get(spec.remote_topic, 0) + 1)

    def _on_keyframe_request(self, topic: str) -> None:
        video = self.videos.get(topic)
        if video is None:
            self.stats.unmatched += 1
            log.info("keyframe request for %s, which this robot does not send as video", topic)
            return
        video.request_keyframe()

    def destroy_node(self) -> None:
        """Stop the video workers (each finishes its frame), then destroy the node."""
        for video in getattr(self, "videos", {}).values():
            video.close()
        super().destroy_node()

    def _next_seq(self, topic: str) -> int:
        # Sequence numbers start at the wall clock in microseconds, so a restarted client's
        # numbers are above its previous run's and receivers' duplicate filters (which drop
        # a no_drop seq not above the last one seen) do not eat its first messages.
        with self._seq_lock:
            seq = self._seq.get(topic, self._clock_ns() // 1000) + 1
            self._seq[topic] = seq
            return seq

    # --- status ----------------------------------------------------------------------------

    def _on_battery(self, msg: Any) -> None:
        percentage = float(msg.percentage)
        # BatteryState uses NaN for "unknown"; keep the last known value in that case.
        if percentage == percentage:
            self._battery = min(max(percentage, 0.0), 1.0)

    def _check_battery_publishers(self) -> None:
        """While no battery level came, name a publisher of ``status.battery_topic`` that
        sends another type (once per type): the page showed no battery, the log nothing."""
        topic = self._config.status.battery_topic
        if topic is None or self._battery is not None:
            return
        for info in self.get_publishers_info_by_topic(topic):
            other = info.topic_type
            if other != BATTERY_TYPE and other not in self._battery_warned:
                self._battery_warned.add(other)
                log.warning("%s (status: battery_topic): a publisher sends %s, not %s: the "
                            "battery level stays unknown", topic, other, BATTERY_TYPE)

    def send_status(self) -> None:
        """Send one RobofleetStatus (battery from the configured topic, if any)."""
        self._check_battery_publishers()
        try:
            frame = self._encode_status(self._battery)
        except Exception as exc:
            self.stats.encode_errors += 1
            log.warning("cannot encode status: %s", exc)
            return
        self._port.send_status(frame)
        self.stats.status_sent += 1

    # --- fleet -> local -----------------------------------------------------------------

    def _bad_local_topic(self, route: _Route, topic: str, reason: str) -> None:
        """Count a frame whose topic cannot be a local topic; say so first and every
        1000th per topic (it was rcl's traceback for every frame)."""
        self.stats.bad_local_topic += 1
        counts = self._refused_frames
        if topic in counts or len(counts) < MAX_REFUSED_NAMES:
            seen = counts[topic] = counts.get(topic, 0) + 1
        else:  # past the bound: sampled over all such topics
            seen = self.stats.bad_local_topic
        if sampled(seen):
            log.warning("dropping %s from the fleet: subscribe entry %s republishes it under "
                        "its own name, which is not a ROS 2 topic name (%s); give the entry a "
                        "local_topic, or rename the topic where it is sent (%d dropped so "
                        "far; logged first and every %dth)", topic, route.spec.remote_topic,
                        reason, seen, LOG_EVERY)

    def deliver(self, frame: bytes) -> None:
        """Publish one frame from the fleet on the local topic of its subscribe entry.

        Never raises: undecodable frames, type mismatches and frames no entry wants are
        counted and logged.
        """
        self.stats.frames_in += 1
        try:
            meta, msg = self._codec.decode(frame)
        except Exception as exc:
            self.stats.decode_errors += 1
            if sampled(self.stats.decode_errors):  # every frame of a broken sender
                log.warning("dropping undecodable frame from the server (%d so far; logged "
                            "first and every %dth): %s", self.stats.decode_errors,
                            LOG_EVERY, exc)
            return
        if meta.type == KEYFRAME_REQUEST_TYPE:  # a viewer of one of our video topics
            self._on_keyframe_request(str(msg.topic))
            return
        route = next((r for r in self._routes if r.matches(meta.topic)), None)
        if route is None:
            self.stats.unmatched += 1
            return
        if meta.type != route.spec.type:
            self.stats.type_mismatch += 1
            # Once per (topic, type), then every 1000th: a wrong type in client.yaml made a
            # WARNING for every message, 10 a second per 10 Hz topic, for ever.
            key = (meta.topic, meta.type)
            seen = self._mismatches.get(key, 0) + 1
            self._mismatches[key] = seen
            if sampled(seen):
                log.warning(
                    "dropping %s on %s: subscribe entry %s expects %s; set its type to %s in "
                    "the client config if that is what it sends (%d dropped so far; logged "
                    "first and every %dth)",
                    meta.type, meta.topic, route.spec.remote_topic, route.spec.type,
                    meta.type, seen, LOG_EVERY)
            return
        try:
            publisher = route.publisher_for(meta.topic, latched=meta.latched,
                                            no_drop=meta.no_drop, frame_bytes=len(frame))
        except BadLocalTopic as exc:
            self._bad_local_topic(route, meta.topic, str(exc))
            return
        if publisher is None:
            self.stats.publishers_over_limit += 1
            return
        try:
            cdr = self._typestore.serialize_cdr(msg, meta.type)
        except Exception as exc:
            self.stats.decode_errors += 1
            if sampled(self.stats.decode_errors):  # every frame of a broken sender
                log.warning("cannot serialize %s from %s, dropped (%d so far; logged first "
                            "and every %dth): %s", meta.type, meta.topic,
                            self.stats.decode_errors, LOG_EVERY, exc)
            return
        publisher.publish(bytes(cdr))
        self.stats.published_local += 1
        if meta.latched:
            self.stats.latched_republished += 1
        elif meta.no_drop:
            self._watch_burst(route, meta.topic)

    def _watch_burst(self, route: _Route, topic: str) -> None:
        """Count a no_drop message published at risk of overwriting one a slow local
        reader has not taken (fleetctl.client.ros.republish.BurstWatch); say so once per
        topic: a loss there is not seen by anything else."""
        depth = route.depth_of(topic)
        if not depth or not self._bursts.published(topic, depth):
            return
        self.stats.no_drop_at_risk += 1
        at_risk = self.stats.per_topic_at_risk
        if topic not in at_risk and len(at_risk) >= MAX_REFUSED_NAMES:
            return  # counted in the total; the per-topic map stays bounded
        at_risk[topic] = at_risk.get(topic, 0) + 1
        if at_risk[topic] == 1:
            log.warning(
                "%s: more than %d no_drop messages of this topic were republished locally "
                "within %.0f s (a backlog the relay delivered at once?): a local subscriber "
                "slower than that may miss the oldest, overwritten in the publisher's "
                "KEEP_LAST %d history before it took them (counted in no_drop_at_risk; "
                "said once per topic)", topic, depth, ACK_WINDOW_S, depth)

