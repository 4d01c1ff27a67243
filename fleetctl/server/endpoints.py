"""HTTP endpoints served on the WebSocket port: ``/healthz``, ``/metrics``, ``/robots``
(and the page's files on the web listener, see :mod:`fleetctl.webviz.httpserver`)."""

from __future__ import annotations

import http
import json
from typing import Any

from websockets.datastructures import Headers
from websockets.http11 import Response

from fleetctl.server.permissions import Permissions

PROMETHEUS_CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


def response(status: http.HTTPStatus, body: bytes, content_type: str,
             cache_control: str = "no-store", shared: bool = False) -> Response:
    """Build a complete HTTP response (no keep-alive: websockets closes after it).

    *cache_control* is ``no-store`` for live data, ``no-cache`` for the page's files
    (kept, but revalidated: they change with the package). *shared*: any origin may read
    it (public data only: the type layouts).
    """
    headers = Headers(
        [
            ("Content-Type", content_type),
            ("Content-Length", str(len(body))),
            ("Connection", "close"),
            ("Cache-Control", cache_control),
        ]
    )
    if shared:
        headers["Access-Control-Allow-Origin"] = "*"
    return Response(status.value, status.phrase, headers, body)


def text(status: http.HTTPStatus, body: str) -> Response:
    """A ``text/plain`` response."""
    return response(status, body.encode(), "text/plain; charset=utf-8")


def json_response(data: Any) -> Response:
    """A 200 ``application/json`` response."""
    return response(http.HTTPStatus.OK, json.dumps(data).encode(), "application/json")


def robots_allowed(
    local: bool, perms: Permissions | None, bad_token: bool
) -> tuple[bool, Permissions | None]:
    """Decide who may read ``/robots`` and ``/metrics`` (docs/security.md).

    Args:
        local: The caller is on loopback and not behind a proxy header
            (:attr:`fleetctl.server.handshake.Upgrade.is_local`).
        perms: Permissions of the caller's identities (address and token), if any.
        bad_token: The caller presented a token that matches no identity.

    Returns:
        ``(allowed, filter)``: *filter* ``None`` means every robot (a loopback caller
        with no identity: the operator on the server machine).
    """
    if bad_token:
        return False, None
    if perms is not None:
        return True, perms
    return local, None
