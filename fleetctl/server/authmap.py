"""The authorization map ``auth.yaml`` (docs/design.md section 3; Robofleet's M).

Each identity is matched by exactly one of ``ip``, ``cidr`` or ``token_sha256`` and owns
rules ``{topic: RE2, op: send|receive|both}``. Nothing is allowed by default; the
permissions of a connection are the union of the rules of every identity it matches.
Tokens are only ever held as SHA-256 hex digests.
"""

from __future__ import annotations

import hmac
import ipaddress
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from fleetctl.errors import ConfigError
from fleetctl.server.regex import BadRegex, FullMatch, compile_full
from fleetctl.tokens import hash_token, is_wellformed_token
from fleetctl.yamlfile import read_yaml

IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network
IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address


class Op(Enum):
    """What a rule allows."""

    SEND = "send"
    RECEIVE = "receive"
    BOTH = "both"

    def allows_send(self) -> bool:
        """Return whether this op grants send."""
        return self is not Op.RECEIVE

    def allows_receive(self) -> bool:
        """Return whether this op grants receive."""
        return self is not Op.SEND


@dataclass(frozen=True)
class Rule:
    """One permission: *op* on every topic that fully matches *topic*."""

    topic: FullMatch
    op: Op

    def as_json(self) -> dict[str, str]:
        """Return the rule as sent in the welcome frame."""
        return {"topic": self.topic.pattern, "op": self.op.value}


@dataclass(frozen=True)
class Identity:
    """One entry of the auth map.

    Attributes:
        name: Label used in logs, metrics and the welcome frame.
        network: The ``ip`` (as a /32 or /128) or ``cidr`` it matches, else ``None``.
        token_sha256: Lower-case hex SHA-256 of its token, else ``None``.
        rules: Its permissions, in file order.
    """

    name: str
    network: IPNetwork | None
    token_sha256: str | None
    rules: tuple[Rule, ...]

    @property
    def by_address(self) -> bool:
        """Whether this identity is matched by network address (robots over WireGuard)."""
        return self.network is not None

    def __repr__(self) -> str:
        # The digest is not the token, but there is no reason to spread it through logs.
        return f"Identity({self.name!r})"


class AuthMap:
    """The loaded auth map: look identities up by address or token."""

    def __init__(self, identities: tuple[Identity, ...]) -> None:
        self.identities = identities
        self._by_digest = {i.token_sha256: i for i in identities if i.token_sha256}
        self._networks = [i for i in identities if i.network is not None]

    def match_address(self, address: IPAddress | None) -> list[Identity]:
        """Return every identity whose ``ip``/``cidr`` contains *address* (file order)."""
        if address is None:
            return []
        return [
            i
            for i in self._networks
            if i.network is not None
            and i.network.version == address.version
            and address in i.network
        ]

    def match_token(self, token: object) -> Identity | None:
        """Return the identity whose ``token_sha256`` is the hash of *token*, or ``None``
        (also for anything that cannot be a token: not a string, non-ASCII, too long)."""
        if not is_wellformed_token(token):
            return None
        assert isinstance(token, str)
        return self.match_digest(hash_token(token))

    def match_digest(self, digest: str) -> Identity | None:
        """Return the identity whose ``token_sha256`` is *digest* (lower-case hex), or
        ``None``; what a reload re-checks a connection's token by (only its hash is kept)."""
        found = self._by_digest.get(digest)
        # Constant-time confirm so the lookup leaks nothing beyond what a dict hit does.
        if found is not None and hmac.compare_digest(found.token_sha256 or "", digest):
            return found
        return None


def load_auth_map(path: Path) -> AuthMap:
    """Read and validate ``auth.yaml``.

    Raises:
        ConfigError: Missing file, bad YAML, or an invalid field; the message names the
            file, the identity and the rule.
    """
    return parse_auth_map(read_yaml(path, "auth map"), path)


def parse_auth_map(raw: Any, path: Path) -> AuthMap:
    """Validate an already-parsed auth map (see :func:`load_auth_map`)."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: top level must be a mapping")
    if raw.get("version", 1) != 1:
        raise ConfigError(f"{path}: field 'version' must be 1")
    items = raw.get("identities") or []
    if not isinstance(items, list):
        raise ConfigError(f"{path}: field 'identities' must be a list")
    identities = tuple(_identity(item, i, path) for i, item in enumerate(items))
    names = [i.name for i in identities]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise ConfigError(f"{path}: identity {dup!r} is defined twice")
    return AuthMap(identities)


def _identity(item: Any, index: int, path: Path) -> Identity:
    where = f"{path}: identities[{index}]"
    if not isinstance(item, dict):
        raise ConfigError(f"{where} must be a mapping")
    name = item.get("name")
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{where}: field 'name' must be a non-empty string")
    name = clean_name(name)
    where = f"{path}: identity {name!r}"
    keys = [k for k in ("ip", "cidr", "token_sha256") if item.get(k) is not None]
    if len(keys) != 1:
        raise ConfigError(f"{where}: set exactly one of 'ip', 'cidr', 'token_sha256'")
    network: IPNetwork | None = None
    digest: str | None = None
    value = str(item[keys[0]])
    try:
        if keys[0] == "ip":
            network = ipaddress.ip_network(ipaddress.ip_address(value))
        elif keys[0] == "cidr":
            network = ipaddress.ip_network(value, strict=False)
    except ValueError:
        raise ConfigError(f"{where}: field {keys[0]!r}: {value!r} is not valid") from None
    if keys[0] == "token_sha256":
        digest = value.lower()
        if len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest):
            raise ConfigError(f"{where}: field 'token_sha256' must be 64 hex digits")
    rules = item.get("rules") or []
    if not isinstance(rules, list):
        raise ConfigError(f"{where}: field 'rules' must be a list")
    return Identity(name, network, digest, tuple(_rule(r, j, where) for j, r in enumerate(rules)))


def clean_name(name: str) -> str:
    """Return *name* as text every sink takes (UTF-8 logs, SQLite, metrics, JSON).

    A YAML writer that escapes non-BMP characters as JSON surrogate pairs
    (``"\\ud83d\\ude00"``) makes the parser return two lone surrogates: a pair is joined
    back into its character; a surrogate left alone becomes its ``\\udXXX`` escape text.
    """
    if not any("\ud800" <= c <= "\udfff" for c in name):
        return name
    joined = name.encode("utf-16-le", "surrogatepass").decode("utf-16-le", "surrogatepass")
    return joined.encode("utf-8", "backslashreplace").decode("utf-8")


def _rule(item: Any, index: int, where: str) -> Rule:
    where = f"{where}: rules[{index}]"
    if not isinstance(item, dict):
        raise ConfigError(f"{where} must be a mapping with 'topic' and 'op'")
    topic, op = item.get("topic"), item.get("op")
    if not isinstance(topic, str):
        raise ConfigError(f"{where}: field 'topic' must be an RE2 regex string")
    try:
        compiled = compile_full(topic)
    except BadRegex as exc:
        raise ConfigError(f"{where}: field 'topic': bad RE2 regex {topic!r}: {exc}") from None
    try:
        return Rule(compiled, Op(op))
    except ValueError:
        raise ConfigError(
            f"{where}: field 'op' must be send, receive or both, not {op!r}"
        ) from None
