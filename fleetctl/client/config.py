"""The robot client's configuration (``client.yaml``), validated on load.

The schema is docs/design.md section 5. Every error is a :class:`fleetctl.errors.ConfigError`
whose message names the file, the entry (index and topic) and the field, e.g.
``client.yaml: publish[2] (/scan): rate_limit_hz: must be > 0 or null, got -1``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fleetctl.client.configfields import Ctx as _Ctx
from fleetctl.client.configfields import boolean as _bool
from fleetctl.client.configfields import integer as _int
from fleetctl.client.configfields import mapping as _mapping
from fleetctl.client.configfields import number as _number
from fleetctl.client.configfields import string as _str
from fleetctl.client.mediaconfig import (
    VIDEO_CODECS,
    VIDEO_TYPES,
    VIEWER_CLOUD_TYPES,
    TfSpec,
    VideoSpec,
    ViewerCloudSpec,
    tf_remote_topics,
    tf_spec,
    video_spec,
    viewer_cloud_spec,
)
from fleetctl.client.serverurls import parse_server_urls
from fleetctl.client.typenames import check_type
from fleetctl.errors import ConfigError
from fleetctl.smallfile import MAX_SECRET_BYTES, read_small_text
from fleetctl.tokens import MAX_TOKEN_CHARS, is_wellformed_token
from fleetctl.yamlfile import read_yaml

# The media keys live in fleetctl.client.mediaconfig; they are imported from here.
__all__ = [
    "COMPRESSIONS", "MAX_FRAGMENT_BYTES", "MIN_FRAGMENT_BYTES", "SCHEDULERS", "VIDEO_CODECS",
    "VIDEO_TYPES", "VIEWER_CLOUD_TYPES", "ClientConfig", "ClientLimits", "PublishSpec",
    "StatusSpec", "SubscribeSpec", "TfSpec", "VideoSpec", "ViewerCloudSpec",
    "load_client_config", "parse_client_config", "tf_remote_topics",
]

# ROS 2 topic names: absolute, tokens of [A-Za-z0-9_] separated by single slashes.
_TOPIC_RE = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")
# rmw's RMW_TOPIC_MAX_NAME_LENGTH (255 - 8: DDS's 256 less the rt/rq/rr prefix and a
# Request/Reply suffix): a longer topic made rcl refuse the node's subscription at start.
MAX_ROS_TOPIC_CHARS = 247
_ROBOT_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,62}$")
_BOM = "\ufeff"

_TOP_KEYS = frozenset(
    {"server_url", "robot_name", "bind_address", "token_file", "publish", "subscribe",
     "status", "limits", "tf"}
)
_PUBLISH_KEYS = frozenset(
    {"topic", "type", "priority", "rate_limit_hz", "no_drop", "remote_topic", "compression",
     "video", "viewer_cloud"}
)
# "none" or a codec of fleetctl.wire.compression (names as in CompressionCodec).
COMPRESSIONS = ("none", "zstd", "deflate")
_SUBSCRIBE_KEYS = frozenset({"remote_topic", "type", "local_topic"})
_STATUS_KEYS = frozenset({"battery_topic", "period_s", "location"})
MAX_LOCATION_CHARS = 200  # a place name for the robot list, not a document
_LIMIT_KEYS = frozenset({"max_fragment_bytes", "no_drop_queue_messages", "reconnect_min_s",
                         "reconnect_max_s", "scheduler", "outage_dial_interval_s",
                         "standby_connection", "dial_ahead_of_messages",
                         "deflate_on_slow_links"})
# The outage dial pace's range: below 5 ms the SYNs sent while down (200/s at 5 ms, ~15 KB/s
# raw, ~26 KB/s inside WireGuard) cost more than the millisecond or two they save; above
# 0.25 s it is the slow pace. The default, 10 ms, is docs/recovery.md's trade-off.
OUTAGE_DIAL_INTERVAL_RANGE_S = (0.005, 0.25)
# adaptive: fragments sized to the link, window from RTT and delivery rate (the default).
# robofleet: the paper's behaviour (whole frames, one frame in flight), for comparison runs.
SCHEDULERS = ("adaptive", "robofleet")

# A fragment must hold the Fragment table's own metadata plus some payload; the server's
# default max_frame_bytes (16 MiB) is the upper end.
MIN_FRAGMENT_BYTES = 512
MAX_FRAGMENT_BYTES = 16 * 1024 * 1024


@dataclass(frozen=True)
class PublishSpec:
    """One local topic sent to the fleet.

    Attributes:
        topic: Local ROS topic, e.g. ``/scan``.
        type: ROS 2 type name in ``pkg/msg/Name`` form.
        priority: Non-negative weight of Algorithm 2 (0 = only when nothing else waits).
        rate_limit_hz: Maximum send rate in Hz; None means no limit.
        no_drop: True for reliable in-order delivery (bounded FIFO), False for latest-only.
        remote_topic: Topic on the wire; defaults to ``/<robot_name><topic>``.
        compression: ``none``, ``zstd`` (fleetctl receivers) or ``deflate`` (also decoded
            by the web page); a frame is sent compressed only when that saves >= 5 %.
        video: Send an image topic as video; None sends the messages as they are.
        viewer_cloud: Also send ``<remote_topic>/viewer`` (a ``ViewerCloud``); None: only
            the full cloud.
    """

    topic: str
    type: str
    priority: float
    rate_limit_hz: float | None
    no_drop: bool
    remote_topic: str
    compression: str = "none"
    video: VideoSpec | None = None
    viewer_cloud: ViewerCloudSpec | None = None


@dataclass(frozen=True)
class SubscribeSpec:
    """One fleet topic (or RE2 regex) received and republished locally.

    Attributes:
        remote_topic: A topic name or an RE2 full-match regex.
        type: ROS 2 type name in ``pkg/msg/Name`` form.
        local_topic: Local topic to republish on. None only when ``remote_topic`` is a regex
            and no local topic was given: each message is republished on its own topic.
    """

    remote_topic: str
    type: str
    local_topic: str | None

    @property
    def is_regex(self) -> bool:
        """True when ``remote_topic`` is not a plain topic name."""
        return _TOPIC_RE.match(self.remote_topic) is None


@dataclass(frozen=True)
class StatusSpec:
    """The client's own ``RobofleetStatus`` on ``/<robot_name>/status``.

    Attributes:
        battery_topic: Local ``sensor_msgs/msg/BatteryState`` topic, or None.
        period_s: Seconds between status messages.
        location: Where the robot is, as people name it (``"warehouse A, aisle 3"``):
            the status's ``location``, shown in the page's robot list; ``""``: not said.
    """

    battery_topic: str | None = None
    period_s: float = 1.0
    location: str = ""


@dataclass(frozen=True)
class ClientLimits:
    """Bounds of the link.

    Attributes:
        max_fragment_bytes: Upper bound of a fragment (bytes); the client sizes fragments
            to about 3 ms of the measured link rate below it.
        no_drop_queue_messages: Bound of the no_drop FIFO, kept across reconnects.
        reconnect_min_s: First reconnect delay in seconds (doubles per failure, jittered).
        reconnect_max_s: Cap of the reconnect delay in seconds.
        scheduler: ``adaptive`` (default) or ``robofleet``: whole frames and one frame in
            flight (Robofleet's n_T = 1), the baseline of comparison runs.
        outage_dial_interval_s: During an outage's first minute, a new TCP connection
            attempt (one SYN) at least this often, seconds: the first SYN after the link
            returns leaves within it. Smaller recovers sooner and sends more while the
            link is down (docs/recovery.md, the dial pace).
        standby_connection: Keep a second, idle connection to the server (when the
            server offers it) and switch to it the moment a cut link returns, instead of
            a WebSocket upgrade on a new connection (docs/recovery.md, the standby
            connection). It costs one more TCP connection per robot; false turns it off.
        dial_ahead_of_messages: During an outage's first minute, also two connection
            attempts before each message a topic is due to publish (its last publish
            plus whole periods), 3 and 1.5 ms ahead of it (more on a path with a long
            SYN round trip), so that a link that returns just before a message has been
            seen to work when it is published (docs/recovery.md, dialing ahead of the
            next message). They take the place of paced SYNs where they fall; at most
            666 a second; false turns it off.
        deflate_on_slow_links: On a link slower than 5 Mbit/s (measured on the wire),
            deflate every message, fragments of large ones too, when the server accepts
            the uplink deflate (docs/wire.md, "Uplink deflate"): ~12 % fewer bytes for a
            camera's images there, for up to ~3 % of a core on the CI host when such
            messages fill the link; false: only messages up to 16 KiB, on any link.
    """

    max_fragment_bytes: int = 4194304
    no_drop_queue_messages: int = 10000
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 5.0
    scheduler: str = "adaptive"
    outage_dial_interval_s: float = 0.01
    standby_connection: bool = True
    dial_ahead_of_messages: bool = True
    deflate_on_slow_links: bool = True


@dataclass(frozen=True)
class ClientConfig:
    """The whole robot client configuration.

    Attributes:
        server_url: ``ws://`` or ``wss://`` URL of the fleet server (the first replica).
        failover_urls: The other replicas' URLs, in the order ``server_url`` lists them
            (:mod:`fleetctl.client.serverurls`).
        robot_name: Namespace prefix of this robot's topics.
        bind_address: Local source address for the connection, or None for any.
        token: Bearer token read from ``token_file``, or None (identified by source IP).
            Never shown in a repr.
        token_file: The file the token was read from (resolved), or None.
        publish: Local topics sent to the fleet.
        subscribe: Fleet topics received and republished locally.
        status: The client's own status messages.
        limits: Link bounds.
        tf: The TF republisher of local ``/tf`` and ``/tf_static``; None: no TF is sent.
    """

    server_url: str
    robot_name: str
    bind_address: str | None = None
    token: str | None = field(default=None, repr=False)
    publish: tuple[PublishSpec, ...] = ()
    subscribe: tuple[SubscribeSpec, ...] = ()
    status: StatusSpec = StatusSpec()
    limits: ClientLimits = ClientLimits()
    tf: TfSpec | None = None
    failover_urls: tuple[str, ...] = ()
    token_file: Path | None = None

    @property
    def server_urls(self) -> tuple[str, ...]:
        """Every replica's URL, ``server_url`` first."""
        return (self.server_url, *self.failover_urls)

    @property
    def status_topic(self) -> str:
        """The remote topic of this robot's status messages."""
        return f"/{self.robot_name}/status"


def load_client_config(path: str | Path) -> ClientConfig:
    """Read and validate a ``client.yaml``.

    Args:
        path: The YAML file. ``token_file`` is resolved relative to its directory.

    Returns:
        The validated configuration.

    Raises:
        ConfigError: The file is missing, not YAML, or an entry is invalid; the message
            names the file, the entry and the field.
    """
    path = Path(path)
    data = read_yaml(path, "client config")
    return parse_client_config(data, source=str(path), base_dir=path.parent)


def parse_client_config(
    data: object, *, source: str = "<client config>", base_dir: Path | None = None
) -> ClientConfig:
    """Validate an already-parsed client config mapping.

    Args:
        data: The YAML document (a mapping).
        source: Name used in error messages (normally the file path).
        base_dir: Directory relative ``token_file`` paths are resolved against; None means
            the current directory.

    Returns:
        The validated configuration.

    Raises:
        ConfigError: An entry is invalid; the message names source, entry and field.
    """
    ctx = _Ctx(source)
    if data is None:  # yaml.safe_load of an empty file; "got NoneType" said nothing
        raise ConfigError(f"{source}: the file is empty (a client config needs at least "
                          "server_url and robot_name)")
    top = _mapping(ctx, data, "", "document", _TOP_KEYS)
    server_url, *failover_urls = parse_server_urls(ctx, top)
    robot_name = _str(ctx, top, "", "robot_name", required=True)
    assert robot_name is not None
    if not _ROBOT_NAME_RE.match(robot_name):
        raise ctx.error("", "robot_name", f"must match [A-Za-z][A-Za-z0-9_]*, got {robot_name!r}")
    publish = _publish_list(ctx, top.get("publish"), robot_name)
    subscribe = _subscribe_list(ctx, top.get("subscribe"))
    tf = tf_spec(ctx, top.get("tf"))
    if tf is not None:
        _check_tf_topics(ctx, publish, subscribe, robot_name)
    _check_loops(ctx, publish, subscribe)
    return ClientConfig(
        server_url=server_url,
        failover_urls=tuple(failover_urls),
        robot_name=robot_name,
        bind_address=_bind_address(ctx, top),
        token=_token(ctx, top, base_dir or Path.cwd()),
        token_file=_token_path(ctx, top, base_dir or Path.cwd()),
        publish=publish,
        subscribe=subscribe,
        status=_status(ctx, top.get("status")),
        limits=_limits(ctx, top.get("limits")),
        tf=tf,
    )


def _topic(
    ctx: _Ctx, entry: Mapping[str, Any], where: str, key: str, *, required: bool
) -> str | None:
    value = _str(ctx, entry, where, key, required=required)
    if value is not None and value.startswith("~"):
        # A node's private name: the client's node (fleetctl_client_NAME) is not the
        # driver whose ~/state it means, and ROS would expand it to the client's own.
        raise ctx.error(where, key, f"{value!r} is private to the node that publishes it "
                        "(~ is that node's namespace and name); write it in full, e.g. "
                        f"/NAMESPACE/NODE{value[1:]} (`ros2 topic list` shows it)")
    if value is not None and not _TOPIC_RE.match(value):
        raise ctx.error(where, key, f"not a ROS topic name (/a/b_c), got {value!r}")
    if value is not None and len(value) > MAX_ROS_TOPIC_CHARS:
        raise ctx.error(where, key, _too_long(value))
    return value


def _too_long(value: str) -> str:
    return (f"{len(value)} characters, ROS 2 allows at most {MAX_ROS_TOPIC_CHARS} (rmw's "
            f"RMW_TOPIC_MAX_NAME_LENGTH), got {value[:40]!r}...")


def _bind_address(ctx: _Ctx, top: Mapping[str, Any]) -> str | None:
    import ipaddress

    value = _str(ctx, top, "", "bind_address")
    if value is None:
        return None
    try:
        ipaddress.ip_address(value)
    except ValueError as exc:
        raise ctx.error("", "bind_address", f"not an IP address: {value!r}") from exc
    return value


def _token_path(ctx: _Ctx, top: Mapping[str, Any], base_dir: Path) -> Path | None:
    value = _str(ctx, top, "", "token_file")
    if value is None:
        return None
    return Path(value) if Path(value).is_absolute() else base_dir / value


def _token(ctx: _Ctx, top: Mapping[str, Any], base_dir: Path) -> str | None:
    path = _token_path(ctx, top, base_dir)
    if path is None:
        return None
    try:
        # A byte order mark (Windows editors write one) is the file's encoding, not the
        # token's: it was sent as part of the token, refused as 4401 'bad token' while
        # the file showed the right one.
        token = read_small_text(path, MAX_SECRET_BYTES).removeprefix(_BOM).strip()
    except OSError as exc:
        raise ctx.error("", "token_file", f"cannot read {path}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError:
        raise ctx.error("", "token_file", f"{path} is not UTF-8 text") from None
    if not token or any(c.isspace() for c in token):
        # Never echo the token itself: it is a secret.
        raise ctx.error("", "token_file", f"{path} must hold one token without whitespace")
    if not is_wellformed_token(token):
        # The relay refuses any other token unseen (fleetctl.tokens): say which character.
        position, char = next(((i, c) for i, c in enumerate(token)
                               if not (c.isascii() and c.isprintable())), (0, ""))
        found = f": U+{ord(char):04X} at character {position + 1}" if char else ""
        raise ctx.error("", "token_file", f"{path}: a token is printable ASCII of at most "
                                          f"{MAX_TOKEN_CHARS} characters{found}")
    return token


def _list(ctx: _Ctx, value: object, name: str) -> list[object]:
    if value is None:
        return []
    if not isinstance(value, list):
        raise ctx.error("", name, f"must be a list, got {type(value).__name__}")
    return value


def _publish_list(ctx: _Ctx, value: object, robot_name: str) -> tuple[PublishSpec, ...]:
    specs: list[PublishSpec] = []
    seen: dict[str, int] = {}
    for i, raw in enumerate(_list(ctx, value, "publish")):
        label = raw.get("topic") if isinstance(raw, Mapping) else None
        where = f"publish[{i}]" + (f" ({label})" if isinstance(label, str) else "")
        spec = _publish(ctx, raw, where, robot_name)
        for remote in _remote_topics(spec):
            if remote in seen:
                reason = f"{remote} is already sent by publish[{seen[remote]}]"
                raise ctx.error(where, "remote_topic", reason)
            seen[remote] = i
        specs.append(spec)
    return tuple(specs)


def _remote_topics(spec: PublishSpec) -> tuple[str, ...]:
    """Every remote topic an entry sends (the viewer cloud is a second one)."""
    if spec.viewer_cloud is None:
        return (spec.remote_topic,)
    return (spec.remote_topic, f"{spec.remote_topic}/viewer")


def _publish(ctx: _Ctx, raw: object, where: str, robot_name: str) -> PublishSpec:
    entry = _mapping(ctx, raw, where, "entry", _PUBLISH_KEYS)
    topic = _topic(ctx, entry, where, "topic", required=True)
    assert topic is not None
    remote = _topic(ctx, entry, where, "remote_topic", required=False)
    priority = _number(ctx, entry, where, "priority", 1.0, lambda v: v >= 0, ">= 0")
    rate = _number(ctx, entry, where, "rate_limit_hz", None, lambda v: v > 0, "> 0 or null")
    remote = remote or f"/{robot_name}{topic}"
    type_name = _type(ctx, entry, where)
    return PublishSpec(
        topic=topic,
        type=type_name,
        priority=1.0 if priority is None else priority,
        rate_limit_hz=rate,
        no_drop=_bool(ctx, entry, where, "no_drop", False),
        remote_topic=remote,
        compression=_compression(ctx, entry, where, remote == f"/{robot_name}/status"),
        video=video_spec(ctx, entry.get("video"), where, type_name),
        viewer_cloud=viewer_cloud_spec(ctx, entry.get("viewer_cloud"), where, type_name),
    )


def _compression(ctx: _Ctx, entry: Mapping[str, Any], where: str, is_status: bool) -> str:
    value = entry.get("compression", "none")
    if value is None:
        value = "none"
    if value not in COMPRESSIONS:
        raise ctx.error(where, "compression", f"must be one of {', '.join(COMPRESSIONS)}, "
                                              f"got {value!r}")
    if is_status and value != "none":
        # The server reads status frames (robot registry) and does not decompress.
        reason = "must be none on the status topic: the server reads status frames as they are"
        raise ctx.error(where, "compression", reason)
    return str(value)


def _subscribe_list(ctx: _Ctx, value: object) -> tuple[SubscribeSpec, ...]:
    specs: list[SubscribeSpec] = []
    for i, raw in enumerate(_list(ctx, value, "subscribe")):
        label = raw.get("remote_topic") if isinstance(raw, Mapping) else None
        where = f"subscribe[{i}]" + (f" ({label})" if isinstance(label, str) else "")
        specs.append(_subscribe(ctx, raw, where))
    return tuple(specs)


def _subscribe(ctx: _Ctx, raw: object, where: str) -> SubscribeSpec:
    entry = _mapping(ctx, raw, where, "entry", _SUBSCRIBE_KEYS)
    remote = _str(ctx, entry, where, "remote_topic", required=True)
    assert remote is not None
    is_topic = _TOPIC_RE.match(remote) is not None
    if not is_topic:
        _check_regex(ctx, where, remote)
    local = _topic(ctx, entry, where, "local_topic", required=False)
    if local is None and is_topic and len(remote) > MAX_ROS_TOPIC_CHARS:
        raise ctx.error(where, "remote_topic", _too_long(remote) + ": set a local_topic")
    return SubscribeSpec(
        remote_topic=remote,
        type=_type(ctx, entry, where),
        local_topic=local if local is not None else (remote if is_topic else None),
    )


def _check_regex(ctx: _Ctx, where: str, pattern: str) -> None:
    # The relay's compiler: RE2 with its own stderr logging off, so that a bad pattern
    # gives this one error line and no absl noise before it.
    from fleetctl.server.regex import BadRegex, compile_full

    try:
        compile_full(pattern)
    except BadRegex as exc:
        reason = f"neither a topic nor a valid RE2 regex: {exc}"
        raise ctx.error(where, "remote_topic", reason) from None


def _type(ctx: _Ctx, entry: Mapping[str, Any], where: str) -> str:
    name = _str(ctx, entry, where, "type", required=True)
    assert name is not None
    normalized, reason = check_type(name)
    if reason:
        raise ctx.error(where, "type", reason)
    return normalized


def _status(ctx: _Ctx, value: object) -> StatusSpec:
    if value is None:
        return StatusSpec()
    entry = _mapping(ctx, value, "status", "entry", _STATUS_KEYS)
    period = _number(ctx, entry, "status", "period_s", 1.0, lambda v: v > 0, "> 0")
    return StatusSpec(
        battery_topic=_topic(ctx, entry, "status", "battery_topic", required=False),
        period_s=1.0 if period is None else period,
        location=_location(ctx, entry),
    )


def location_problem(value: str) -> str | None:
    """What is wrong with *value* as a robot's status location, or None (also used for
    fleet.yaml's ``robots[].location``, which becomes this)."""
    if len(value) > MAX_LOCATION_CHARS or not value.isprintable():
        return (f"must be one line of at most {MAX_LOCATION_CHARS} printable characters, "
                f"got {value[:40]!r}")
    return None


def _location(ctx: _Ctx, entry: Mapping[str, Any]) -> str:
    value = _str(ctx, entry, "status", "location") or ""
    problem = location_problem(value)
    if problem is not None:
        raise ctx.error("status", "location", problem)
    return value


def _check_tf_topics(ctx: _Ctx, publish: tuple[PublishSpec, ...],
                     subscribe: tuple[SubscribeSpec, ...], robot_name: str) -> None:
    # The republisher owns these two remote topics; a publish entry sending them too would
    # interleave raw and throttled TF on one topic.
    owned = set(tf_remote_topics(robot_name))
    for i, spec in enumerate(publish):
        if spec.remote_topic in owned:
            reason = f"{spec.remote_topic} is sent by the tf section; remove this entry or tf"
            raise ctx.error(f"publish[{i}] ({spec.topic})", "remote_topic", reason)
    # ... and reads local /tf and /tf_static: another robot's TF republished there would
    # go out again as this robot's own (docs/robot.md said so; nothing refused it).
    for i, sub in enumerate(subscribe):
        if sub.local_topic in ("/tf", "/tf_static"):
            reason = (f"{sub.local_topic} is read by the tf section, which would send what "
                      f"arrives there as {robot_name}'s own TF; republish it under a topic of "
                      f"its own (e.g. {sub.local_topic}_{_remote_robot(sub.remote_topic)})")
            raise ctx.error(f"subscribe[{i}] ({sub.remote_topic})", "local_topic", reason)


def _remote_robot(remote_topic: str) -> str:
    """The first name of a remote topic (``/husky1/tf`` -> ``husky1``), for a hint."""
    first = remote_topic.strip("/").split("/")[0]
    return first if _ROBOT_NAME_RE.match(first) else "remote"


def _check_loops(ctx: _Ctx, publish: tuple[PublishSpec, ...],
                 subscribe: tuple[SubscribeSpec, ...]) -> None:
    """A subscribe entry that republishes this robot's own published topic onto the local
    topic it is published from: every message would come back and go out again, for ever
    (the relay delivers a sender's frames to its own subscriptions)."""
    from fleetctl.server.regex import compile_full

    for i, sub in enumerate(subscribe):
        if sub.local_topic is None:
            continue
        receives = compile_full(sub.remote_topic)
        for j, pub in enumerate(publish):
            if pub.topic == sub.local_topic and receives.matches(pub.remote_topic):
                reason = (f"{sub.local_topic} is publish[{j}]'s topic, sent as "
                          f"{pub.remote_topic}, which this entry receives: every message would "
                          "loop back to the fleet; give it another local_topic")
                raise ctx.error(f"subscribe[{i}] ({sub.remote_topic})", "local_topic", reason)


def _limits(ctx: _Ctx, value: object) -> ClientLimits:
    if value is None:
        return ClientLimits()
    entry = _mapping(ctx, value, "limits", "entry", _LIMIT_KEYS)
    d = ClientLimits()
    lo = _number(ctx, entry, "limits", "reconnect_min_s", d.reconnect_min_s, lambda v: v > 0, "> 0")
    hi = _number(ctx, entry, "limits", "reconnect_max_s", d.reconnect_max_s, lambda v: v > 0, "> 0")
    assert lo is not None and hi is not None
    if hi < lo:
        raise ctx.error("limits", "reconnect_max_s", f"must be >= reconnect_min_s ({lo}), got {hi}")
    return ClientLimits(
        max_fragment_bytes=_int(ctx, entry, "limits", "max_fragment_bytes", d.max_fragment_bytes,
                                MIN_FRAGMENT_BYTES, MAX_FRAGMENT_BYTES),
        no_drop_queue_messages=_int(ctx, entry, "limits", "no_drop_queue_messages",
                                    d.no_drop_queue_messages, 1, 10_000_000),
        reconnect_min_s=lo,
        reconnect_max_s=hi,
        scheduler=_scheduler(ctx, entry),
        outage_dial_interval_s=_outage_dial_interval(ctx, entry, d.outage_dial_interval_s),
        standby_connection=_bool(ctx, entry, "limits", "standby_connection",
                                 d.standby_connection),
        dial_ahead_of_messages=_bool(ctx, entry, "limits", "dial_ahead_of_messages",
                                     d.dial_ahead_of_messages),
        deflate_on_slow_links=_bool(ctx, entry, "limits", "deflate_on_slow_links",
                                    d.deflate_on_slow_links),
    )


def _outage_dial_interval(ctx: _Ctx, entry: Mapping[str, Any], default: float) -> float:
    low, high = OUTAGE_DIAL_INTERVAL_RANGE_S
    value = _number(ctx, entry, "limits", "outage_dial_interval_s", default,
                    lambda v: low <= v <= high, f"between {low} and {high}")
    assert value is not None
    return value


def _scheduler(ctx: _Ctx, entry: Mapping[str, Any]) -> str:
    value = entry.get("scheduler", "adaptive")
    if value not in SCHEDULERS:
        raise ctx.error("limits", "scheduler",
                        f"must be one of {', '.join(SCHEDULERS)}, got {value!r}")
    return str(value)
