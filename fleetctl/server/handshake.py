"""What an HTTP request or WebSocket upgrade says about its sender, read once and safely.

:func:`read_request` runs in websockets' ``process_request``, before anything is created
for the connection, and either returns an :class:`Upgrade` or raises
:class:`~fleetctl.server.identity.BadRequest` (answered 400). Every header is read with
:func:`~fleetctl.server.identity.one_header` or
:func:`~fleetctl.server.identity.list_header`: a repeated ``Authorization`` header is a 400,
never an exception escaping into websockets (a 500 with a traceback, docs/security.md).

:class:`HandshakeLog` turns websockets' "opening handshake failed" tracebacks (a port
scan, a POST, a malformed request) into one line.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from websockets.asyncio.server import ServerConnection
from websockets.http11 import Request

from fleetctl.server.authmap import IPAddress, IPNetwork
from fleetctl.server.identity import (
    PROXY_HEADERS,
    BadRequest,
    bearer_token,
    effective_address,
    list_header,
    one_header,
    parse_address,
    within,
)
from fleetctl.server.sessions import SESSION_HEADER, STANDBY_HEADER

__all__ = ["BadRequest", "HandshakeLog", "Upgrade", "read_request", "wants_websocket"]


@dataclass(frozen=True)
class Upgrade:
    """The identity-relevant parts of one request.

    Attributes:
        address: The address to match ``ip``/``cidr`` identities against (the TCP peer,
            or the nearest untrusted ``X-Forwarded-For`` hop behind a trusted proxy).
        token: The ``Authorization: Bearer`` token as sent (``None``: no such header);
            never in a repr.
        session_name: ``X-Fleetctl-Session`` (several headers joined: an invalid name,
            refused on authentication), or ``None``.
        proxied_loopback: The TCP peer is loopback and not a trusted proxy, yet the request
            carries a proxy header: a same-host reverse proxy nobody listed in
            ``trusted_proxies``. Such a request gets no loopback privilege.
        standby: ``X-Fleetctl-Standby: 1`` (only with a session header): a robot's
            standby connection of its session (see
            :meth:`~fleetctl.server.relay.RelayCore.activate`).
    """

    address: IPAddress | None
    token: str | None = field(repr=False)
    session_name: str | None
    proxied_loopback: bool = False
    standby: bool = False

    @property
    def is_local(self) -> bool:
        """Whether the request comes from this machine (loopback, not through a proxy)."""
        return (self.address is not None and self.address.is_loopback
                and not self.proxied_loopback)


def read_request(connection: ServerConnection, request: Request,
                 trusted_proxies: tuple[IPNetwork, ...]) -> Upgrade:
    """Read who sent *request*.

    Raises:
        BadRequest: A header that must appear once appears several times, or a bad
            ``X-Fleetctl-Standby`` header.
    """
    headers = request.headers
    remote = connection.remote_address
    peer = parse_address(remote[0] if remote else None)
    forwarded = list_header(headers, "X-Forwarded-For")
    address = effective_address(peer, forwarded, trusted_proxies)
    token = bearer_token(one_header(headers, "Authorization"))
    names = headers.get_all(SESSION_HEADER)
    standby = _standby(one_header(headers, STANDBY_HEADER), bool(names))
    proxied = (peer is not None and peer.is_loopback and not within(peer, trusted_proxies)
               and any(name in headers for name in PROXY_HEADERS))
    return Upgrade(address, token, ",".join(names) if names else None, proxied, standby)


def _standby(value: str | None, has_session: bool) -> bool:
    """Whether an ``X-Fleetctl-Standby`` header *value* marks a standby connection.

    Raises:
        BadRequest: A value other than ``1``, or no session header.
    """
    if value is None:
        return False
    if value.strip() != "1":
        raise BadRequest(f"{STANDBY_HEADER}: {value[:40]!r} is not 1 (the only value)")
    if not has_session:
        raise BadRequest(f"{STANDBY_HEADER} without {SESSION_HEADER}: a standby connection "
                         "is one of a named session")
    return True


def wants_websocket(request: Request) -> bool:
    """Whether *request* asks for a WebSocket upgrade (else it is a plain GET)."""
    return any(v.strip().lower() == "websocket" for v in request.headers.get_all("Upgrade"))


class HandshakeLog(logging.Filter):
    """One line instead of a traceback for a failed opening handshake.

    websockets logs ``opening handshake failed`` at ERROR with the traceback for every
    request it cannot parse or refuses (a port scan, a POST, a half-sent request): noise
    that anyone can write into the log. The line becomes ``opening handshake failed:
    <reason>`` at INFO; nothing is logged when the peer went away before sending a
    request (a port scan, or a connection refused by the unauthenticated caps, which are
    counted in ``fleetctl_connections_refused_total``).
    """

    def filter(self, record: logging.LogRecord) -> bool:
        """Rewrite the record in place; drop it when the peer sent no request at all."""
        if record.msg != "opening handshake failed" or not record.exc_info:
            return True
        exc = record.exc_info[1]
        if isinstance(exc, EOFError) or isinstance(getattr(exc, "__cause__", None), EOFError):
            return False
        record.exc_info = None
        record.exc_text = None
        record.msg = "opening handshake failed: %s"
        record.args = (_reason(exc),)
        record.levelno = logging.INFO
        record.levelname = "INFO"
        return True


def _reason(exc: BaseException | None) -> str:
    parts: list[str] = []
    while exc is not None and len(parts) < 3:
        parts.append(str(exc) or type(exc).__name__)
        exc = exc.__cause__
    return ": ".join(parts)[:300]
