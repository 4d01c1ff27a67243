"""Who is on the other end of a connection (docs/design.md section 2, "Identity").

Address identities use the TCP peer address; ``X-Forwarded-For`` replaces it only when
the peer itself is a configured trusted proxy (anyone can set the header). Tokens come
from ``Authorization: Bearer`` on the upgrade or from a first text frame
``{"token": "..."}`` (browsers cannot set headers on a WebSocket upgrade).
"""

from __future__ import annotations

import ipaddress
import json
from collections.abc import Iterable

from websockets.datastructures import Headers

from fleetctl.server.authmap import IPAddress, IPNetwork

# Why a cap: the token frame arrives before the client is known; never parse megabytes.
MAX_TOKEN_FRAME_CHARS = 4096


# Headers a reverse proxy sets; from an untrusted peer they are ignored (and, from
# loopback, a sign of an unconfigured same-host proxy: see docs/security.md).
PROXY_HEADERS = ("X-Forwarded-For", "Forwarded", "X-Real-IP")


class BadRequest(ValueError):
    """A request the server answers with 400; the message says why."""


def one_header(headers: Headers, name: str) -> str | None:
    """The value of a header that may appear at most once, or ``None`` if absent.

    Raises:
        BadRequest: The header appears more than once (which one would count is
            ambiguous: a proxy and the client may each have set one).
    """
    values = headers.get_all(name)
    if len(values) > 1:
        raise BadRequest(f"{len(values)} {name} headers: send one")
    return values[0] if values else None


def list_header(headers: Headers, name: str) -> str | None:
    """A comma-separated list header, repeated headers joined (RFC 9110 5.3)."""
    values = headers.get_all(name)
    return ", ".join(values) if values else None


def parse_address(text: str | None) -> IPAddress | None:
    """Parse an IP address (IPv4-mapped IPv6 becomes IPv4); ``None`` if not an address."""
    if not text:
        return None
    try:
        addr = ipaddress.ip_address(text.strip().split("%", 1)[0])
    except ValueError:
        return None
    if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
        return addr.ipv4_mapped
    return addr


def effective_address(
    peer: IPAddress | None,
    forwarded_for: str | None,
    trusted_proxies: Iterable[IPNetwork],
) -> IPAddress | None:
    """Return the address to match ``ip``/``cidr`` identities against.

    Args:
        peer: The TCP peer address.
        forwarded_for: The ``X-Forwarded-For`` header value, or ``None``.
        trusted_proxies: Networks whose header is believed.

    Returns:
        The peer, or, when the peer is a trusted proxy, the right-most address of the
        header that is not itself a trusted proxy (the nearest untrusted hop: entries to
        its left were written by the client and may be forged). ``None`` if unknown.
    """
    proxies = tuple(trusted_proxies)
    if peer is None or not forwarded_for or not _within(peer, proxies):
        return peer
    hops = [parse_address(h) for h in forwarded_for.split(",")]
    for hop in reversed(hops):
        if hop is None:
            return None  # a garbled chain: trust nothing in it
        if not _within(hop, proxies):
            return hop
    return peer


def within(addr: IPAddress | None, networks: Iterable[IPNetwork]) -> bool:
    """Whether *addr* is in one of *networks* (``False`` for ``None``)."""
    return addr is not None and _within(addr, tuple(networks))


def _within(addr: IPAddress, networks: tuple[IPNetwork, ...]) -> bool:
    return any(addr.version == n.version and addr in n for n in networks)


def bearer_token(authorization: str | None) -> str | None:
    """Return the token of an ``Authorization: Bearer TOKEN`` header, else ``None``."""
    if not authorization:
        return None
    scheme, _, token = authorization.strip().partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        return None
    return token.strip()


def token_from_frame(text: str) -> str | None:
    """Return the token of a ``{"token": "..."}`` text frame, or ``None`` if it is not one."""
    if len(text) > MAX_TOKEN_FRAME_CHARS:
        return None
    try:
        data = json.loads(text)
    except ValueError:
        return None
    if not isinstance(data, dict):
        return None
    token = data.get("token")
    return token if isinstance(token, str) and token else None
