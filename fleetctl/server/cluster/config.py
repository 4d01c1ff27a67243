"""The ``cluster:`` section of ``server.yaml`` (docs/scaling.md).

Example::

    cluster:
      name: relay-a                      # this replica, in NATS and in logs
      nats_urls: [nats://10.8.0.1:4222, nats://10.8.0.2:4222]
      credentials:                       # optional; exactly one kind
        creds_file: relay-a.creds        # a NATS .creds file (JWT + NKey seed)
        # nkey_seed_file: relay-a.nk     # an NKey seed
        # user: relay-a                  # user + password read from a file
        # password_file: relay-a.password
      subject_prefix: fleetctl           # first token of every subject
      publish_queue_frames: 8192         # frames waiting for NATS; more are dropped (counted)
      publish_queue_bytes: 16777216
      connect_timeout_s: 2
      state_replicas: 1                  # copies of the shared robot registry (3 on 3 nodes)
      session_stream_bytes: 1073741824   # no_drop frames kept for sessions, all replicas

Only paths are kept: the secret is read when connecting, so it is in no repr or log line.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import SplitResult, urlsplit

from fleetctl.errors import ConfigError
from fleetctl.server.configsection import is_positive_number, section
from fleetctl.smallfile import MAX_SECRET_BYTES, read_small_text

_KEYS = {"name", "nats_urls", "credentials", "subject_prefix", "publish_queue_frames",
         "publish_queue_bytes", "connect_timeout_s", "state_replicas",
         "session_stream_bytes"}
_CRED_KEYS = {"creds_file", "nkey_seed_file", "user", "password_file"}
_SCHEMES = {"nats", "tls"}
# A subject token of our own (the prefix) and a replica name: no NATS wildcards or dots.
_TOKEN = re.compile(r"[A-Za-z0-9_-]{1,64}")


class ClusterStartError(Exception):
    """NATS cannot be joined at start: no server answers (the message names
    ``cluster.nats_urls``) or the credentials are refused (``cluster.credentials``)."""


@dataclass(frozen=True)
class NatsCredentials:
    """How this replica authenticates to NATS (one of the three kinds).

    Attributes:
        creds_file: A ``.creds`` file (user JWT and NKey seed), or ``None``.
        nkey_seed_file: An NKey seed file, or ``None``.
        user: A user name (with ``password_file``), or ``None``.
        password_file: A file whose first line is the password, or ``None``.
    """

    creds_file: Path | None = None
    nkey_seed_file: Path | None = None
    user: str | None = None
    password_file: Path | None = None

    def read_password(self) -> str:
        """The password (first line of ``password_file``), read now, never stored.

        Raises:
            OSError: The file cannot be read.
        """
        assert self.password_file is not None
        return read_small_text(self.password_file, MAX_SECRET_BYTES).splitlines()[0]


@dataclass(frozen=True)
class ClusterConfig:
    """This replica's place in a NATS cluster.

    Attributes:
        name: Replica name (NATS client name, log lines, metrics).
        nats_urls: NATS server URLs (``nats://host:port``); tried in order, then on
            reconnect whichever answers.
        credentials: NATS credentials, or ``None`` for a server without authentication.
        subject_prefix: First token of every subject (one fleet per prefix).
        publish_queue_frames: Frames waiting to be handed to the NATS client; past it an
            accepted frame is not published to other replicas (counted ``queue_full``).
        publish_queue_bytes: The same bound in bytes.
        connect_timeout_s: Seconds to reach a NATS server at start before giving up.
        state_replicas: Copies JetStream keeps of the shared state (the robot registry's
            KV bucket): 1 survives a replica's death, 3 on a 3-node NATS cluster also a
            NATS node's (JetStream allows 1 to 5).
        session_stream_bytes: Bytes of no_drop frames the sessions' JetStream stream
            keeps for every replica's sessions together (oldest out first; also bounded
            in age by ``session_expiry_s``).
    """

    name: str
    nats_urls: tuple[str, ...]
    credentials: NatsCredentials | None = None
    subject_prefix: str = "fleetctl"
    publish_queue_frames: int = 8192
    publish_queue_bytes: int = 16 * 1024 * 1024
    connect_timeout_s: float = 2.0
    state_replicas: int = 1
    session_stream_bytes: int = 1024 * 1024 * 1024


def parse_cluster(value: Any, base: Path, path: Path) -> ClusterConfig | None:
    """Validate the ``cluster:`` mapping; ``None`` (absent) means a single process.

    Raises:
        ConfigError: A field is invalid (the message names the file and the field).
    """
    value = section(value, _KEYS, "cluster", path)
    if value is None:
        return None
    return ClusterConfig(
        name=_token(value, "name", None, path),
        nats_urls=_urls(value.get("nats_urls"), path),
        credentials=_credentials(value.get("credentials"), base, path),
        subject_prefix=_token(value, "subject_prefix", "fleetctl", path),
        publish_queue_frames=_positive(value, "publish_queue_frames", 8192, path),
        publish_queue_bytes=_positive(value, "publish_queue_bytes", 16 * 1024 * 1024, path),
        connect_timeout_s=float(_positive(value, "connect_timeout_s", 2.0, path)),
        state_replicas=_state_replicas(value, path),
        session_stream_bytes=_positive(value, "session_stream_bytes", 1024 * 1024 * 1024,
                                       path),
    )


def _state_replicas(raw: dict[str, Any], path: Path) -> int:
    value = _positive(raw, "state_replicas", 1, path)
    if value > 5:  # JetStream's limit on a stream's replicas
        raise ConfigError(f"{path}: field 'cluster.state_replicas' must be 1 to 5, got {value}")
    return int(value)


def _token(raw: dict[str, Any], name: str, default: str | None, path: Path) -> str:
    value = raw.get(name, default)
    if not isinstance(value, str) or not _TOKEN.fullmatch(value):
        raise ConfigError(f"{path}: field 'cluster.{name}' must be 1-64 characters of "
                          "A-Z a-z 0-9 _ -")
    return value


def _positive(raw: dict[str, Any], name: str, default: float, path: Path) -> Any:
    value = raw.get(name, default)
    if not is_positive_number(value):
        raise ConfigError(f"{path}: field 'cluster.{name}' must be a positive number")
    if isinstance(default, int) and not isinstance(value, int):
        raise ConfigError(f"{path}: field 'cluster.{name}' must be a positive integer")
    return value


def _urls(value: Any, path: Path) -> tuple[str, ...]:
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{path}: field 'cluster.nats_urls' must be a non-empty list of "
                          "nats://host:port URLs")
    for i, url in enumerate(value):
        parts = _split(url)
        if parts is None or parts.scheme not in _SCHEMES or not parts.hostname:
            raise ConfigError(f"{path}: field 'cluster.nats_urls[{i}]': {url!r} is not a "
                              "nats://host:port URL")
        if parts.password is not None:  # a secret in a URL ends up in logs: refuse it
            raise ConfigError(f"{path}: field 'cluster.nats_urls[{i}]': put credentials "
                              "in 'cluster.credentials', not in the URL")
    return tuple(value)


def _split(url: Any) -> SplitResult | None:
    """*url*'s parts, or ``None`` when it is no URL with a valid host and port:
    ``urlsplit`` raises ValueError for a bad bracketed host (``tls://[]::1]:4222``), and
    reading ``port`` for one out of range or not a number."""
    if not isinstance(url, str):
        return None
    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018 - read for its check
    except ValueError:
        return None
    return parts


def _credentials(value: Any, base: Path, path: Path) -> NatsCredentials | None:
    value = section(value, _CRED_KEYS, "cluster.credentials", path)
    if value is None:
        return None
    kinds = [k for k in ("creds_file", "nkey_seed_file", "user") if k in value]
    if len(kinds) != 1:
        raise ConfigError(f"{path}: field 'cluster.credentials': give exactly one of "
                          "creds_file, nkey_seed_file, or user with password_file")
    if ("user" in value) != ("password_file" in value):
        raise ConfigError(f"{path}: field 'cluster.credentials': user and password_file "
                          "go together")
    files = {k: _secret_file(value, k, base, path) for k in value if k.endswith("_file")}
    user = value.get("user")
    if user is not None and (not isinstance(user, str) or not user):
        raise ConfigError(f"{path}: field 'cluster.credentials.user' must be a string")
    return NatsCredentials(user=user, **files)


def _secret_file(raw: dict[str, Any], name: str, base: Path, path: Path) -> Path:
    value = raw[name]
    field = f"cluster.credentials.{name}"
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{path}: field '{field}' must be a path string")
    found = base / value
    if not found.is_file() or not os.access(found, os.R_OK):
        raise ConfigError(f"{path}: field '{field}': {found} is not a readable file")
    if found.stat().st_size == 0:
        raise ConfigError(f"{path}: field '{field}': {found} is empty")
    return found
