"""Which source addresses count as one client for the per-address bounds (docs/security.md).

An IPv4 address is one client. An IPv6 host gets a whole /64 (SLAAC and the privacy
addresses of RFC 8981 pick any address inside it, and a host can add as many as it
likes), so counting each IPv6 address on its own let one host fill a per-address cap of
256 from 256 of its own addresses: a /64 counts as one client. An IPv4-mapped IPv6
address (``::ffff:203.0.113.9``, an IPv4 peer of a dual-stack socket) is its IPv4 address.
"""

from __future__ import annotations

import ipaddress

from fleetctl.server.identity import parse_address

# The prefix that one IPv6 client holds (RFC 4291 2.5.1: interface identifiers are 64 bits).
IPV6_CLIENT_PREFIX = 64


def address_group(address: str | None) -> str:
    """The key under which *address* is counted.

    Args:
        address: A peer address as text (``"203.0.113.9"``, ``"2001:db8::1"``,
            ``"::ffff:203.0.113.9"``, with or without a ``%scope``), or ``None``.

    Returns:
        The IPv4 address (``"203.0.113.9"``), the IPv6 /64 (``"2001:db8::/64"``), or, for
        text that is not an address (a Unix socket, a test's name), the text itself
        (``"?"`` for ``None``).
    """
    parsed = parse_address(address)
    if parsed is None:
        return address or "?"
    if parsed.version == 6:
        return str(ipaddress.ip_network((parsed, IPV6_CLIENT_PREFIX), strict=False))
    return str(parsed)
