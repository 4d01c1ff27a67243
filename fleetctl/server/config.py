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

import re2

from fleetctl.errors import ConfigError
from fleetctl.yamlfile import read_yaml

DEFAULT_PORT = 8080


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


@dataclass(frozen=True)
class ServerConfig:
    """Everything ``fleetctl server`` needs to run.

    Attributes:
        listen_host: Address to bind.
        listen_port: TCP port to bind; 0 picks a free port.
        auth_map: Path of the auth map (``auth.yaml``).
        database: Path of the SQLite robot registry; ``None`` keeps it in memory.
        tls_cert: PEM certificate path, or ``None`` for plain ``ws://``.
        tls_key: PEM private key path, or ``None``; set together with ``tls_cert``.
        trusted_proxies: Networks whose ``X-Forwarded-For`` header is believed.
        no_drop_topics: RE2 full-match patterns of topics always treated as no_drop.
        limits: Resource bounds.
    """

    listen_host: str = "0.0.0.0"
    listen_port: int = DEFAULT_PORT
    auth_map: Path = Path("auth.yaml")
    database: Path | None = Path("fleet.db")
    tls_cert: Path | None = None
    tls_key: Path | None = None
    trusted_proxies: tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...] = ()
    no_drop_topics: tuple[str, ...] = ()
    limits: ServerLimits = field(default_factory=ServerLimits)


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
}
_INT_LIMITS = (
    "max_frame_bytes",
    "max_subscriptions_per_connection",
    "outbound_queue_bytes",
    "outbound_no_drop_messages",
    "max_malformed_in_row",
    "session_mailbox_messages",
    "session_mailbox_bytes",
    "max_sessions_per_identity",
)
_FLOAT_LIMITS = ("robot_offline_after_s", "auth_timeout_s", "session_expiry_s")


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
    unknown = sorted(set(raw) - _TOP_KEYS)
    if unknown:
        raise ConfigError(f"{path}: unknown field {unknown[0]!r}")
    base = path.parent
    cert = _opt_path(raw, "tls_cert", base, path)
    key = _opt_path(raw, "tls_key", base, path)
    if (cert is None) != (key is None):
        raise ConfigError(f"{path}: field 'tls_cert'/'tls_key': set both or neither")
    return ServerConfig(
        listen_host=_str(raw, "listen_host", "0.0.0.0", path),
        listen_port=_port(raw, path),
        auth_map=_req_path(raw, "auth_map", base, path),
        database=_opt_path(raw, "database", base, path, default="fleet.db"),
        tls_cert=cert,
        tls_key=key,
        trusted_proxies=_networks(raw.get("trusted_proxies") or [], path),
        no_drop_topics=_regexes(raw.get("no_drop_topics") or [], path),
        limits=_limits(raw.get("limits") or {}, path),
    )


def _str(raw: dict[str, Any], name: str, default: str, path: Path) -> str:
    value = raw.get(name, default)
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{path}: field {name!r} must be a non-empty string")
    return value


def _port(raw: dict[str, Any], path: Path) -> int:
    value = raw.get("listen_port", DEFAULT_PORT)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 65535:
        raise ConfigError(f"{path}: field 'listen_port' must be an integer 0..65535")
    return int(value)


def _req_path(raw: dict[str, Any], name: str, base: Path, path: Path) -> Path:
    value = _opt_path(raw, name, base, path, default=None)
    if value is None:
        raise ConfigError(f"{path}: field {name!r} is required")
    return value


def _opt_path(
    raw: dict[str, Any], name: str, base: Path, path: Path, default: str | None = None
) -> Path | None:
    value = raw.get(name, default)
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{path}: field {name!r} must be a path string or null")
    return base / value


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
            re2.compile(item)
        except re2.error as exc:
            raise ConfigError(
                f"{path}: field 'no_drop_topics[{i}]': bad RE2 regex {item!r}: {exc}"
            ) from None
    return tuple(value)


def _limits(value: Any, path: Path) -> ServerLimits:
    if not isinstance(value, dict):
        raise ConfigError(f"{path}: field 'limits' must be a mapping")
    known = set(_INT_LIMITS) | set(_FLOAT_LIMITS)
    unknown = sorted(set(value) - known)
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
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v <= 0:
                raise ConfigError(f"{path}: field 'limits.{name}' must be a positive number")
            kwargs[name] = float(v)
    return ServerLimits(**kwargs)
