"""A robot's topics in ``fleet.yaml`` (``publish``, ``subscribe``, ``battery_topic``), their
default set (docs/design.md section 7), and their checks.

The rules match what the robot client accepts in ``client.yaml``
(:mod:`fleetctl.client.config`), so every fleet that validates renders a client config the
client loads: absolute topic names of ``[A-Za-z0-9_]`` tokens, ``priority >= 0``,
``rate_limit_hz > 0`` or ``null``, compression ``none | zstd | deflate``, a message
type the wire registry knows (the rosbags ROS 2 Jazzy store plus fleetctl's shipped types)
or the fleet's own definitions define (``FLEET/msg_types``, :mod:`fleetctl.deploy.msgtypes`),
``video`` only on image topics and ``viewer_cloud`` only on point clouds (the client's own
spec classes and limits are reused, so the two cannot drift apart).
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import re
from dataclasses import dataclass

import yaml

from fleetctl.client.config import (
    VIDEO_CODECS,
    VIDEO_TYPES,
    VIEWER_CLOUD_TYPES,
    TfSpec,
    VideoSpec,
    ViewerCloudSpec,
)
from fleetctl.deploy.msgtypes import HOW_TO_ADD, NO_MSG_TYPES, FleetMsgTypes
from fleetctl.deploy.yamlnodes import Document, FieldPath, FleetInvalid, shown
from fleetctl.server.regex import BadRegex, compile_full

# As fleetctl.client.config: absolute, tokens of [A-Za-z0-9_] separated by single slashes.
TOPIC = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")
# "none" or a codec of fleetctl.wire.compression; the same tuple as the client's COMPRESSIONS.
COMPRESSIONS = ("none", "zstd", "deflate")
# The client publishes its own RobofleetStatus on /<robot>/status.
STATUS_TOPIC = "/status"
# With a robot's ``tf:`` section the client sends /<robot>/tf and /<robot>/tf_static itself.
TF_TOPICS = ("/tf", "/tf_static")
# A viewer cloud goes out as <remote_topic>/viewer beside the full cloud.
VIEWER_SUFFIX = "/viewer"
MAX_BITRATE_KBPS = 1_000_000  # as the client: 1 Gbit/s is no camera's bitrate
DEFAULT_PRIORITY = 1.0  # the client's default


@dataclass(frozen=True)
class PublishTopic:
    """A local topic the robot client sends to the fleet (``publish:`` in client.yaml).

    Attributes:
        topic: the local ROS topic; it goes out as ``/<robot><topic>``.
        type: ROS 2 type name.
        priority: weight in the client's fair-priority queue (higher goes first), >= 0.
        rate_limit_hz: at most this many messages per second; ``None``: no limit.
        no_drop: reliable, in-order delivery (never replaced by a newer message).
        compression: ``none``, ``zstd`` or ``deflate`` (deflate if a web page shows it).
        video: send an image topic as video (``foxglove_msgs/msg/CompressedVideo``);
            ``None``: as it is.
        viewer_cloud: also send ``/<robot><topic>/viewer`` (a voxelized ``ViewerCloud``);
            ``None``: only the full cloud.
    """

    topic: str
    type: str
    priority: float
    rate_limit_hz: float | None
    no_drop: bool = False
    compression: str = "none"
    video: VideoSpec | None = None
    viewer_cloud: ViewerCloudSpec | None = None


@dataclass(frozen=True)
class SubscribeTopic:
    """A fleet topic the robot receives and republishes locally (beyond its command topics).

    Attributes:
        remote_topic: the fleet topic, e.g. ``/husky1/map``; the robot is allowed to
            receive it (auth.yaml) because it is listed here.
        type: ROS 2 type name.
        local_topic: where it is republished on the robot; ``None``: the remote name.
    """

    remote_topic: str
    type: str
    local_topic: str | None = None

    @property
    def local(self) -> str:
        """The local topic it is republished on."""
        return self.local_topic or self.remote_topic


# Why these numbers: localization and odometry are small and what an operator watches most,
# so they go first and fast; scans next; camera and point clouds are big and only useful
# fresh, so they are rate-limited hardest and yield to everything else. /map is the
# latched occupancy grid. /events is the
# robot's log of discrete happenings, which must all arrive (no_drop). /status is sent by
# the client itself and is not listed here.
DEFAULT_PUBLISH: tuple[PublishTopic, ...] = (
    PublishTopic("/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", 5.0, 10.0),
    PublishTopic("/odom", "nav_msgs/msg/Odometry", 4.0, 10.0),
    PublishTopic("/scan", "sensor_msgs/msg/LaserScan", 3.0, 10.0),
    PublishTopic("/camera/image/compressed", "sensor_msgs/msg/CompressedImage", 1.0, 5.0),
    PublishTopic("/points", "sensor_msgs/msg/PointCloud2", 0.5, 2.0),
    # Nav2's map_server and SLAM publish it latched: the client follows that QoS, the server
    # keeps the last one for viewers who open the page later (deflated when large).
    PublishTopic("/map", "nav_msgs/msg/OccupancyGrid", 0.5, 1.0),
    PublishTopic("/events", "std_msgs/msg/String", 10.0, None, no_drop=True),
)


# --- checks ----------------------------------------------------------------------------


@functools.cache
def _known_types() -> frozenset[str]:
    # Imported here: building the registry parses ~170 definitions (~0.25 s), paid once and
    # only by commands that validate a fleet.
    from fleetctl.wire.registry import TypeRegistry

    return frozenset(TypeRegistry.default().names())


def check_type(name: str, path: FieldPath, own: FleetMsgTypes = NO_MSG_TYPES) -> None:
    """Raise :class:`FleetInvalid` unless *name* is a ROS 2 type the wire registry knows
    or the fleet's own definitions (*own*, ``FLEET/msg_types``) define.

    ``pkg/Name`` is accepted as ``pkg/msg/Name``, as the client does.
    """
    from fleetctl.wire.errors import WireError
    from fleetctl.wire.metadata import normalize_type

    try:
        normalized = normalize_type(name)
    except WireError:
        raise FleetInvalid(path, f"{name!r} is not a ROS type name (pkg/msg/Name)") from None
    if normalized not in _known_types() and normalized not in own.names:
        raise FleetInvalid(path, _unknown_type(name, normalized, own))


def _unknown_type(name: str, normalized: str, own: FleetMsgTypes) -> str:
    # As the robot client's message (fleetctl.client.typenames): where it looked, the
    # closest known name, and what to do for a package of the fleet's own.
    close = difflib.get_close_matches(normalized, sorted(_known_types() | own.names), n=1,
                                      cutoff=0.8)
    hint = f" Did you mean {close[0]}?" if close else ""
    package = normalized.partition("/msg/")[0]
    return (f"unknown ROS type {name!r}: not a ROS 2 Jazzy or fleetctl type, and the "
            f"fleet's own definitions do not have it ({own.where(normalized)}).{hint} A "
            f"package of your own: {HOW_TO_ADD.replace('PKG', package)}, then render")


def check_regex(pattern: str, path: FieldPath) -> None:
    """Raise :class:`FleetInvalid` unless the relay accepts *pattern*.

    The relay's own compiler decides (RE2, its length bound, UTF-8 text): a pattern that
    passed a separate check here could render into an auth.yaml the server refuses at start.
    """
    try:
        compile_full(pattern)
    except BadRegex as exc:
        raise FleetInvalid(path, f"not a valid RE2 regex {shown(pattern)}: {exc}") from None


def check_topic(topic: str, path: FieldPath) -> None:
    """Raise :class:`FleetInvalid` unless *topic* is an absolute ROS topic name."""
    if not TOPIC.fullmatch(topic):
        raise FleetInvalid(path, f"{topic!r} is not an absolute ROS topic name (/a/b_c)")


def check_publish(publish: tuple[PublishTopic, ...], path: FieldPath,
                  own: FleetMsgTypes = NO_MSG_TYPES) -> None:
    """Check a robot's ``publish`` list (*path* is the list's field path; *own*: the
    fleet's own message types)."""
    seen: dict[str, int] = {}
    for j, p in enumerate(publish):
        where = (*path, j)
        check_topic(p.topic, (*where, "topic"))
        if p.topic == STATUS_TOPIC:
            raise FleetInvalid((*where, "topic"), "/status is sent by the client itself "
                               "(fleetctl_msgs/msg/RobofleetStatus); pick another name")
        if p.topic in seen:
            other = format_index(path, seen[p.topic])
            raise FleetInvalid((*where, "topic"), f"duplicate topic {p.topic!r} (also {other})")
        seen[p.topic] = j
        check_type(p.type, (*where, "type"), own)
        _check_numbers(p, where)
        if p.compression not in COMPRESSIONS:
            raise FleetInvalid((*where, "compression"), f"must be one of "
                               f"{', '.join(COMPRESSIONS)}, got {p.compression!r}")
        _check_video(p, where)
        _check_viewer_cloud(p, where)
    _check_viewer_names(publish, path)


def check_tf(tf: TfSpec | None, publish: tuple[PublishTopic, ...], path: FieldPath) -> None:
    """Check a robot's ``tf`` section against its ``publish`` list (*path*: the robot's)."""
    if tf is None:
        return
    where = (*path, "tf")
    if not tf.translation_delta_m >= 0:
        raise FleetInvalid((*where, "translation_delta_m"),
                           f"must be >= 0, got {tf.translation_delta_m}")
    if not 0 <= tf.rotation_delta_rad <= math.pi:
        raise FleetInvalid((*where, "rotation_delta_rad"),
                           f"must be between 0 and pi, got {tf.rotation_delta_rad}")
    if not 0 < tf.max_rate_hz <= 1000:
        raise FleetInvalid((*where, "max_rate_hz"), f"must be > 0 and <= 1000, got "
                                                    f"{tf.max_rate_hz}")
    for j, p in enumerate(publish):
        if p.topic in TF_TOPICS:
            raise FleetInvalid((*path, "publish", j, "topic"), f"{p.topic} is sent by the "
                               "robot's tf section (throttled); remove this entry or tf")


def _check_video(p: PublishTopic, where: FieldPath) -> None:
    v = p.video
    if v is None:
        return
    if _normalized(p.type) not in VIDEO_TYPES:
        raise FleetInvalid((*where, "video"), f"only for {' or '.join(VIDEO_TYPES)}, "
                                              f"not {p.type}")
    if v.codec not in VIDEO_CODECS:
        raise FleetInvalid((*where, "video", "codec"),
                           f"must be one of {', '.join(VIDEO_CODECS)}, got {v.codec!r}")
    if v.min_bitrate_kbps > v.max_bitrate_kbps:
        raise FleetInvalid((*where, "video", "min_bitrate_kbps"), f"must be <= "
                           f"max_bitrate_kbps ({v.max_bitrate_kbps}), got {v.min_bitrate_kbps}")
    if not v.keyframe_interval_s > 0:
        raise FleetInvalid((*where, "video", "keyframe_interval_s"),
                           f"must be > 0, got {v.keyframe_interval_s}")


def _check_viewer_cloud(p: PublishTopic, where: FieldPath) -> None:
    c = p.viewer_cloud
    if c is None:
        return
    if _normalized(p.type) not in VIEWER_CLOUD_TYPES:
        raise FleetInvalid((*where, "viewer_cloud"), f"only for {VIEWER_CLOUD_TYPES[0]}, "
                                                     f"not {p.type}")
    if not 0.001 <= c.resolution_m <= 1.0:
        raise FleetInvalid((*where, "viewer_cloud", "resolution_m"),
                           f"must be between 0.001 and 1, got {c.resolution_m}")


def _check_viewer_names(publish: tuple[PublishTopic, ...], path: FieldPath) -> None:
    # The client refuses a config where /<robot><topic>/viewer is also another entry's topic.
    topics = {p.topic: j for j, p in enumerate(publish)}
    for j, p in enumerate(publish):
        viewer = p.topic + VIEWER_SUFFIX
        if p.viewer_cloud is not None and viewer in topics:
            other = format_index(path, topics[viewer])
            raise FleetInvalid((*path, j, "viewer_cloud"), f"its viewer topic {viewer!r} is "
                               f"also {other}'s topic")


def _normalized(name: str) -> str:
    from fleetctl.wire.metadata import normalize_type

    return normalize_type(name)  # check_type ran first: the name is well formed


def format_index(path: FieldPath, index: int) -> str:
    """Return ``publish[3]`` for the list field *path* and *index*."""
    return f"{path[-1]}[{index}]"


def _check_numbers(p: PublishTopic, where: FieldPath) -> None:
    if not p.priority >= 0:
        raise FleetInvalid((*where, "priority"), f"must be >= 0, got {p.priority}")
    if p.rate_limit_hz is not None and not p.rate_limit_hz > 0:
        raise FleetInvalid((*where, "rate_limit_hz"), f"must be > 0 or null, got {p.rate_limit_hz}")


def check_subscribe(subscribe: tuple[SubscribeTopic, ...], taken: dict[str, str],
                    path: FieldPath, own: FleetMsgTypes = NO_MSG_TYPES) -> None:
    """Check a robot's ``subscribe`` list.

    Args:
        subscribe: the entries.
        taken: remote and local topics already used (by the command topics), each mapped
            to what uses it; updated in place.
        path: the list's field path.
        own: the fleet's own message types.
    """
    for j, s in enumerate(subscribe):
        where = (*path, j)
        check_topic(s.remote_topic, (*where, "remote_topic"))
        if s.local_topic is not None:
            check_topic(s.local_topic, (*where, "local_topic"))
        check_type(s.type, (*where, "type"), own)
        for key, field_name in ((f"remote {s.remote_topic}", "remote_topic"),
                                (f"local {s.local}", "local_topic")):
            if key in taken:
                raise FleetInvalid((*where, field_name),
                                   f"{key.split()[1]!r} is already received by {taken[key]}")
            taken[key] = format_index(path, j)


# --- fleet.yaml ------------------------------------------------------------------------

_PUBLISH_FIELDS = ["priority", "rate_limit_hz", "no_drop", "compression", "video",
                   "viewer_cloud"]
_VIDEO_FIELDS = ["codec", "max_bitrate_kbps", "min_bitrate_kbps", "keyframe_interval_s"]
_TF_FIELDS = ["translation_delta_m", "rotation_delta_rad", "max_rate_hz"]


def build_publish(doc: Document, node: yaml.Node, path: FieldPath) -> tuple[PublishTopic, ...]:
    """Read a ``publish`` list (missing optional fields take the client's defaults)."""
    return tuple(_build_one_publish(doc, n, (*path, j))
                 for j, n in enumerate(doc.sequence(node, path)))


def _build_one_publish(doc: Document, node: yaml.Node, path: FieldPath) -> PublishTopic:
    f = doc.mapping(node, path, ["topic", "type"], _PUBLISH_FIELDS)
    rate = None
    if "rate_limit_hz" in f and not doc.is_null(f["rate_limit_hz"]):
        rate = doc.number(f["rate_limit_hz"], (*path, "rate_limit_hz"))
    compression = "none"
    if "compression" in f:
        compression = doc.optional_string(f["compression"], (*path, "compression")) or "none"
    return PublishTopic(
        topic=doc.string(f["topic"], (*path, "topic")),
        type=doc.string(f["type"], (*path, "type")),
        priority=(doc.number(f["priority"], (*path, "priority")) if "priority" in f
                  else DEFAULT_PRIORITY),
        rate_limit_hz=rate,
        no_drop=doc.boolean(f["no_drop"], (*path, "no_drop")) if "no_drop" in f else False,
        compression=compression,
        video=_build_video(doc, f, path),
        viewer_cloud=_build_viewer_cloud(doc, f, path),
    )


def _optional_mapping(doc: Document, f: dict[str, yaml.Node], key: str, path: FieldPath,
                      fields: list[str]) -> dict[str, yaml.Node] | None:
    """The fields of an optional sub-mapping; ``None`` when absent or ``null``."""
    if key not in f or doc.is_null(f[key]):
        return None
    return doc.mapping(f[key], (*path, key), [], fields)


def _build_video(doc: Document, f: dict[str, yaml.Node], path: FieldPath) -> VideoSpec | None:
    v = _optional_mapping(doc, f, "video", path, _VIDEO_FIELDS)
    if v is None:
        return None
    where = (*path, "video")
    d = VideoSpec()
    return VideoSpec(
        codec=doc.string(v["codec"], (*where, "codec")) if "codec" in v else d.codec,
        max_bitrate_kbps=(doc.integer(v["max_bitrate_kbps"], (*where, "max_bitrate_kbps"), 1,
                                      MAX_BITRATE_KBPS)
                          if "max_bitrate_kbps" in v else d.max_bitrate_kbps),
        min_bitrate_kbps=(doc.integer(v["min_bitrate_kbps"], (*where, "min_bitrate_kbps"), 1,
                                      MAX_BITRATE_KBPS)
                          if "min_bitrate_kbps" in v else d.min_bitrate_kbps),
        keyframe_interval_s=(doc.number(v["keyframe_interval_s"],
                                        (*where, "keyframe_interval_s"))
                             if "keyframe_interval_s" in v else d.keyframe_interval_s),
    )


def _build_viewer_cloud(doc: Document, f: dict[str, yaml.Node],
                        path: FieldPath) -> ViewerCloudSpec | None:
    c = _optional_mapping(doc, f, "viewer_cloud", path, ["resolution_m"])
    if c is None:
        return None
    if "resolution_m" not in c:
        return ViewerCloudSpec()
    return ViewerCloudSpec(doc.number(c["resolution_m"], (*path, "viewer_cloud", "resolution_m")))


def build_tf(doc: Document, f: dict[str, yaml.Node], path: FieldPath) -> TfSpec | None:
    """Read a robot's optional ``tf`` section (*f*: the robot's fields, *path*: its path)."""
    t = _optional_mapping(doc, f, "tf", path, _TF_FIELDS)
    if t is None:
        return None
    d = TfSpec()
    values = {k: doc.number(t[k], (*path, "tf", k)) if k in t else getattr(d, k)
              for k in _TF_FIELDS}
    return TfSpec(**values)


def build_subscribe(doc: Document, node: yaml.Node,
                    path: FieldPath) -> tuple[SubscribeTopic, ...]:
    """Read a ``subscribe`` list."""
    out = []
    for j, n in enumerate(doc.sequence(node, path)):
        where = (*path, j)
        f = doc.mapping(n, where, ["remote_topic", "type"], ["local_topic"])
        local = (doc.optional_string(f["local_topic"], (*where, "local_topic"))
                 if "local_topic" in f else None)
        out.append(SubscribeTopic(doc.string(f["remote_topic"], (*where, "remote_topic")),
                                  doc.string(f["type"], (*where, "type")), local))
    return tuple(out)


def dump_publish(publish: tuple[PublishTopic, ...]) -> list[dict[str, object]]:
    """Return the ``fleet.yaml`` form of a ``publish`` list (every field written out;
    ``video`` and ``viewer_cloud`` only where set, so older fleets keep their bytes)."""
    out = []
    for p in publish:
        item: dict[str, object] = {
            "topic": p.topic, "type": p.type, "priority": p.priority,
            "rate_limit_hz": p.rate_limit_hz, "no_drop": p.no_drop,
            "compression": p.compression}
        if p.video is not None:
            item["video"] = dataclasses.asdict(p.video)
        if p.viewer_cloud is not None:
            item["viewer_cloud"] = dataclasses.asdict(p.viewer_cloud)
        out.append(item)
    return out


def dump_tf(tf: TfSpec) -> dict[str, object]:
    """Return the ``fleet.yaml`` form of a robot's ``tf`` section."""
    return dict(dataclasses.asdict(tf))


def dump_subscribe(subscribe: tuple[SubscribeTopic, ...]) -> list[dict[str, object]]:
    """Return the ``fleet.yaml`` form of a ``subscribe`` list."""
    return [{"remote_topic": s.remote_topic, "type": s.type, "local_topic": s.local_topic}
            for s in subscribe]
