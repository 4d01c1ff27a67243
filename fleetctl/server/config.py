"""Server configuration (``server.yaml``, docs/design.md section 4).

One frozen dataclass per concern, units in field names. :func:`load_server_config` reads
the YAML file and raises :class:`~fleetctl.errors.ConfigError` naming the file and the
field at fault; it never returns a half-valid config.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fleetctl.errors import ConfigError
from fleetctl.server.cluster.config import ClusterConfig, parse_cluster
from fleetctl.server.configsection import is_positive_number, section
from fleetctl.server.msgtypes import MsgTypes, parse_msg_types
from fleetctl.server.recording.config import RecordingConfig, parse_recording
from fleetctl.server.regex import BadRegex, compile_full
from fleetctl.server.tls import server_context
from fleetctl.smallfile import MAX_PEM_BYTES, read_small
from fleetctl.webviz.config import DEBIAN_JS_DIR
from fleetctl.yamlfile import read_yaml

DEFAULT_PORT = 8080
DEFAULT_WEB_PORT = 8443

Hosts = str | tuple[str, ...]
"""One address to bind, or several (e.g. the WireGuard address and 127.0.0.1)."""


@dataclass(frozen=True)
class ServerLimits:
    """Resource bounds of the relay.

    Attributes:
        max_frame_bytes: Largest WebSocket frame accepted, bytes; larger closes with 1009.
        max_subscriptions_per_connection: Subscriptions one connection may hold; one more
            is refused, and a flood past twice this closes the connection with 4429.
        outbound_queue_bytes: Bytes one connection may have queued for sending, all topics.
        outbound_no_drop_messages: Messages the per-connection no_drop FIFO may hold.
        robot_offline_after_s: Seconds without a frame after which a robot is offline.
        max_malformed_in_row: Consecutive malformed frames that close with 1007.
        auth_timeout_s: Seconds a connection with no identity has to send its token frame.
        session_expiry_s: Seconds a named session may stay without a connection before it
            is dropped (its subscriptions and mailbox are forgotten).
        session_mailbox_messages: no_drop frames one offline session's mailbox holds;
            more drop the oldest (counted).
        session_mailbox_bytes: Bytes one offline session's mailbox holds (same policy).
        max_sessions_per_identity: Named sessions one identity set may hold at a time;
            a connection naming one more closes with 4400.
        max_connections_per_identity: Open authenticated connections per identity name;
            one more closes with 4429 (a robot's address identity and a person's token
            each count separately).
        max_control_requests_per_s: Sustained rate of control requests per connection
            (subscribe/unsubscribe frames, token frames, ``list_robots``) per identity
            set, per second; bursts of ``max_subscriptions_per_connection`` (at least 64)
            pass (a full resubscribe after a reconnect). Over it a request is refused
            with ``rate_limited``.
        max_pattern_bytes_per_connection: UTF-8 bytes of subscription patterns one
            connection may hold; one more pattern is refused (``too_many_subscriptions``).
        max_pattern_bytes_per_identity: The same over every connection of one identity.
        max_unauthenticated_connections: Connections (handshake included) without an
            identity yet, server-wide; more are aborted at accept.
        max_unauthenticated_per_address: The same per TCP source address (trusted
            proxies are exempt: they carry many clients).
        latched_bytes: Bytes of latched messages the server keeps, all senders and topics
            (the last message per sender and topic, fragments of one still arriving
            included); past it the least recently updated are evicted (counted). Also
            the bound of latched frames queued for one connection at a time.
        latched_message_bytes: Largest latched message kept (its frames, or its fragment
            frames, together), bytes; a larger one is relayed but not kept (counted), and
            the sender's older message on that topic is forgotten.
        keyframe_request_interval_s: At most one keyframe request per video topic is
            forwarded to its publisher per this many seconds; more are counted, dropped.
    """

    max_frame_bytes: int = 16 * 1024 * 1024
    max_subscriptions_per_connection: int = 256
    outbound_queue_bytes: int = 8 * 1024 * 1024
    outbound_no_drop_messages: int = 1024
    robot_offline_after_s: float = 5.0
    max_malformed_in_row: int = 10
    auth_timeout_s: float = 10.0
    session_expiry_s: float = 3600.0
    session_mailbox_messages: int = 10000
    session_mailbox_bytes: int = 16 * 1024 * 1024
    max_sessions_per_identity: int = 64
    max_connections_per_identity: int = 64
    max_control_requests_per_s: float = 20.0
    max_pattern_bytes_per_connection: int = 64 * 1024
    max_pattern_bytes_per_identity: int = 1024 * 1024
    max_unauthenticated_connections: int = 256
    max_unauthenticated_per_address: int = 16
    latched_bytes: int = 64 * 1024 * 1024
    latched_message_bytes: int = 16 * 1024 * 1024
    keyframe_request_interval_s: float = 0.25


@dataclass(frozen=True)
class WebConfig:
    """The web listener: the page and the relay's WebSocket on one HTTPS origin.

    Attributes:
        tls_cert: PEM certificate path (required: browsers need a secure origin).
        tls_key: PEM private key path (required).
        listen_host: Address or addresses to bind.
        listen_port: TCP port; 0 picks a free port.
        vendor_dir: Directory holding Debian's ``three/`` and ``leaflet/``.
        replica_ports: HTTPS ports of every relay replica on the page's host, as the
            browser reaches them (``fleetctl up --replicas`` writes them): the page
            fails over to the same host name on the next port when its replica goes.
    """

    tls_cert: Path
    tls_key: Path
    listen_host: Hosts = "0.0.0.0"
    listen_port: int = DEFAULT_WEB_PORT
    vendor_dir: Path = DEBIAN_JS_DIR
    replica_ports: tuple[int, ...] = ()


@dataclass(frozen=True)
class ServerConfig:
    """Everything ``fleetctl server`` needs to run.

    Attributes:
        listen_host: Address to bind, or a tuple of addresses (each is bound).
        listen_port: TCP port to bind; 0 picks a free port (per address).
        auth_map: Path of the auth map (``auth.yaml``).
        database: Path of the SQLite robot registry; ``None`` keeps it in memory.
        tls_cert: PEM certificate path, or ``None`` for plain ``ws://``.
        tls_key: PEM private key path, or ``None``; set together with ``tls_cert``.
        trusted_proxies: Networks whose ``X-Forwarded-For`` header is believed.
        no_drop_topics: RE2 full-match patterns of topics always treated as no_drop.
        limits: Resource bounds.
        web: The HTTPS web listener (page + WebSocket), or ``None`` for none.
        recording: MCAP recording (docs/server.md, "Recording"), or ``None`` for none.
        cluster: Relay replicas on NATS (docs/scaling.md), or ``None``: one process.
        msg_types: The fleet's own message types, ``(pkg/msg/Name, .msg text)`` pairs, for
            the web page's layouts and the Foxglove listener
            (:mod:`fleetctl.server.msgtypes`).
    """

    listen_host: Hosts = "0.0.0.0"
    listen_port: int = DEFAULT_PORT
    auth_map: Path = Path("auth.yaml")
    database: Path | None = Path("fleet.db")
    tls_cert: Path | None = None
    tls_key: Path | None = None
    trusted_proxies: tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...] = ()
    no_drop_topics: tuple[str, ...] = ()
    limits: ServerLimits = field(default_factory=ServerLimits)
    web: WebConfig | None = None
    recording: RecordingConfig | None = None
    cluster: ClusterConfig | None = None
    msg_types: MsgTypes = ()


def host_list(hosts: Hosts) -> list[str]:
    """Return *hosts* as a list (what ``loop.create_server`` is given)."""
    return [hosts] if isinstance(hosts, str) else list(hosts)


def hosts_text(hosts: Hosts) -> str:
    """*hosts* for messages: ``0.0.0.0`` or ``10.8.0.1,127.0.0.1``."""
    return ",".join(host_list(hosts))


_TOP_KEYS = {
    "listen_host",
    "listen_port",
    "auth_map",
    "database",
    "tls_cert",
    "tls_key",
    "trusted_proxies",
    "no_drop_topics",
    "limits",
    "web",
    "recording",
    "cluster",
    "msg_types",
}
_WEB_KEYS = {"listen_host", "listen_port", "tls_cert", "tls_key", "vendor_dir",
             "replica_ports"}
MAX_REPLICA_PORTS = 16
_INT_LIMITS = (
    "max_frame_bytes",
    "max_subscriptions_per_connection",
    "outbound_queue_bytes",
    "outbound_no_drop_messages",
    "max_malformed_in_row",
    "session_mailbox_messages",
    "session_mailbox_bytes",
    "max_sessions_per_identity",
    "max_connections_per_identity",
    "max_pattern_bytes_per_connection",
    "max_pattern_bytes_per_identity",
    "max_unauthenticated_connections",
    "max_unauthenticated_per_address",
    "latched_bytes",
    "latched_message_bytes",
)
_FLOAT_LIMITS = ("robot_offline_after_s", "auth_timeout_s", "session_expiry_s",
                 "max_control_requests_per_s", "keyframe_request_interval_s")


def load_server_config(path: Path) -> ServerConfig:
    """Read and validate ``server.yaml``.

    Args:
        path: The config file; relative paths inside it are relative to its directory.

    Returns:
        The validated config.

    Raises:
        ConfigError: The file is missing, not YAML, or a field is invalid (the message
            names the file and the field).
    """
    raw = read_yaml(path, "server config")
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: top level must be a mapping")
    return parse_server_config(raw, path)


def parse_server_config(raw: dict[str, Any], path: Path) -> ServerConfig:
    """Validate an already-parsed ``server.yaml`` mapping (see :func:`load_server_config`)."""
    unknown = sorted(set(raw) - _TOP_KEYS, key=str)  # YAML keys may be numbers or null
    if unknown:
        raise ConfigError(f"{path}: unknown field {unknown[0]!r}")
    base = path.parent
    cert = _opt_path(raw, "tls_cert", base, path)
    key = _opt_path(raw, "tls_key", base, path)
    if (cert is None) != (key is None):
        raise ConfigError(f"{path}: field 'tls_cert'/'tls_key': set both or neither")
    if cert is not None and key is not None:
        _check_tls(cert, key, "", path)
    return ServerConfig(
        listen_host=_hosts(raw, "listen_host", path),
        listen_port=_port(raw, "listen_port", DEFAULT_PORT, path),
        auth_map=_req_path(raw, "auth_map", base, path),
        database=_opt_path(raw, "database", base, path, default="fleet.db"),
        tls_cert=cert,
        tls_key=key,
        trusted_proxies=_networks(raw.get("trusted_proxies") or [], path),
        no_drop_topics=_regexes(raw.get("no_drop_topics") or [], path),
        limits=_limits(raw.get("limits") or {}, path),
        web=_web(raw.get("web"), base, path),
        recording=parse_recording(raw.get("recording"), base, path),
        cluster=parse_cluster(raw.get("cluster"), base, path),
        msg_types=parse_msg_types(raw.get("msg_types"), path),
    )


def _hosts(raw: dict[str, Any], name: str, path: Path, prefix: str = "") -> Hosts:
    value = raw.get(name, "0.0.0.0")
    if isinstance(value, str) and value:
        return value
    if (isinstance(value, list) and value
            and all(isinstance(v, str) and v for v in value)):
        return tuple(value)
    raise ConfigError(f"{path}: field '{prefix}{name}' must be an address or a non-empty "
                      "list of addresses")


def _port(raw: dict[str, Any], name: str, default: int, path: Path) -> int:
    value = raw.get(name.rpartition(".")[2], default)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 65535:
        raise ConfigError(f"{path}: field {name!r} must be an integer 0..65535")
    return int(value)


def _web(value: Any, base: Path, path: Path) -> WebConfig | None:
    value = section(value, _WEB_KEYS, "web", path)
    if value is None:
        return None
    cert = _readable(value, "tls_cert", base, path)
    key = _readable(value, "tls_key", base, path)
    _check_tls(cert, key, "web.", path)
    vendor = _opt_path(value, "vendor_dir", base, path, default=str(DEBIAN_JS_DIR), prefix="web.")
    assert vendor is not None
    return WebConfig(
        tls_cert=cert,
        tls_key=key,
        listen_host=_hosts(value, "listen_host", path, prefix="web."),
        listen_port=_port(value, "web.listen_port", DEFAULT_WEB_PORT, path),
        vendor_dir=vendor,
        replica_ports=_replica_ports(value.get("replica_ports"), path),
    )


def _replica_ports(value: Any, path: Path) -> tuple[int, ...]:
    if value is None:
        return ()
    if not isinstance(value, list) or len(value) > MAX_REPLICA_PORTS:
        raise ConfigError(f"{path}: field 'web.replica_ports' must be a list of at most "
                          f"{MAX_REPLICA_PORTS} ports")
    for i, port in enumerate(value):
        if isinstance(port, bool) or not isinstance(port, int) or not 0 < port < 65536:
            raise ConfigError(f"{path}: field 'web.replica_ports[{i}]': {port!r} is not a "
                              "port 1..65535")
    if len(set(value)) != len(value):
        raise ConfigError(f"{path}: field 'web.replica_ports' lists a port twice")
    return tuple(value)


def _readable(raw: dict[str, Any], name: str, base: Path, path: Path) -> Path:
    found = _opt_path(raw, name, base, path, prefix="web.")
    if found is None:
        raise ConfigError(f"{path}: field 'web.{name}' is required (a PEM file)")
    try:
        read_small(found, MAX_PEM_BYTES)  # opening a FIFO must not hang the server's start
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise ConfigError(f"{path}: field 'web.{name}': cannot read {found}: {reason}") from None
    return found


def _check_tls(cert: Path, key: Path, prefix: str, path: Path) -> None:
    """Load the pair once now, so a bad one is a config error, not a traceback at start."""
    try:
        server_context(cert, key)
    except ConfigError as exc:
        raise ConfigError(f"{path}: field '{prefix}tls_cert'/'{prefix}tls_key': {exc}") from None


def _req_path(raw: dict[str, Any], name: str, base: Path, path: Path) -> Path:
    value = _opt_path(raw, name, base, path, default=None)
    if value is None:
        raise ConfigError(f"{path}: field {name!r} is required")
    return value


def _opt_path(
    raw: dict[str, Any], name: str, base: Path, path: Path, default: str | None = None,
    prefix: str = "",
) -> Path | None:
    value = raw.get(name, default)
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{path}: field '{prefix}{name}' must be a path string or null")
    if "\0" in value:  # YAML's "\0" escape: open(), ssl and sqlite3 raise ValueError
        raise ConfigError(f"{path}: field '{prefix}{name}' must be a path without a NUL byte")
    return base / value  # an absolute value stays absolute


def _networks(
    value: Any, path: Path
) -> tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...]:
    if not isinstance(value, list):
        raise ConfigError(f"{path}: field 'trusted_proxies' must be a list of IPs/CIDRs")
    nets = []
    for i, item in enumerate(value):
        try:
            nets.append(ipaddress.ip_network(str(item), strict=False))
        except ValueError:
            raise ConfigError(
                f"{path}: field 'trusted_proxies[{i}]': {item!r} is not an IP or CIDR"
            ) from None
    return tuple(nets)


def _regexes(value: Any, path: Path) -> tuple[str, ...]:
    if not isinstance(value, list):
        raise ConfigError(f"{path}: field 'no_drop_topics' must be a list of RE2 regexes")
    for i, item in enumerate(value):
        if not isinstance(item, str):
            raise ConfigError(f"{path}: field 'no_drop_topics[{i}]' must be a string")
        try:
            compile_full(item)  # RE2 with its stderr logging off, as every relay regex
        except BadRegex as exc:
            raise ConfigError(
                f"{path}: field 'no_drop_topics[{i}]': bad RE2 regex {item!r}: {exc}"
            ) from None
    return tuple(value)


def _limits(value: Any, path: Path) -> ServerLimits:
    if not isinstance(value, dict):
        raise ConfigError(f"{path}: field 'limits' must be a mapping")
    known = set(_INT_LIMITS) | set(_FLOAT_LIMITS)
    unknown = sorted(set(value) - known, key=str)
    if unknown:
        raise ConfigError(f"{path}: unknown field 'limits.{unknown[0]}'")
    kwargs: dict[str, Any] = {}
    for name in _INT_LIMITS:
        if name in value:
            v = value[name]
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ConfigError(f"{path}: field 'limits.{name}' must be a positive integer")
            kwargs[name] = v
    for name in _FLOAT_LIMITS:
        if name in value:
            v = value[name]
            if not is_positive_number(v):
                raise ConfigError(f"{path}: field 'limits.{name}' must be a positive number, "
                                  f"got {v!r}")
            kwargs[name] = float(v)
    return ServerLimits(**kwargs)
