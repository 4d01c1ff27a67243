"""HTTP endpoints served on the WebSocket port: ``/healthz``, ``/metrics``, ``/robots``,
``/login-budget`` (and the page's files on the web listener, see
:mod:`fleetctl.webviz.httpserver`)."""

from __future__ import annotations

import http
import json
import math
from typing import Any

from websockets.datastructures import Headers
from websockets.http11 import Response

from fleetctl.server.permissions import Permissions

PROMETHEUS_CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
# Where a page on any origin asks whether its address is over its failed-login budget.
LOGIN_BUDGET_PATH = "/login-budget"


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


def too_many_logins(retry_after_s: float) -> Response:
    """429 for a request whose address is over its failed-login budget (its token was
    not looked at), with ``Retry-After`` in whole seconds (RFC 9110 10.2.3)."""
    seconds = max(1, math.ceil(retry_after_s))
    reply = text(http.HTTPStatus.TOO_MANY_REQUESTS, "too many failed logins from this "
                 f"address: retry in {seconds} s\n")
    reply.headers["Retry-After"] = str(seconds)
    return reply


def login_budget(retry_after_s: float) -> Response:
    """The answer to ``GET /login-budget``: 204 while the caller's address is within its
    failed-login budget (*retry_after_s* 0), else the 429 its token would get.

    Any origin may read it (docs/security.md, "Failed logins"): a browser hides a refused
    WebSocket upgrade's status, and the page may be served from another origin than the
    relay's. It says one thing about the caller's own address, which that caller could
    learn by presenting any token; no credentials are asked for or allowed.
    """
    if retry_after_s > 0:
        reply = too_many_logins(retry_after_s)
    else:  # RFC 9110 8.6: no Content-Length on a 204
        reply = Response(http.HTTPStatus.NO_CONTENT.value, http.HTTPStatus.NO_CONTENT.phrase,
                         Headers([("Connection", "close"), ("Cache-Control", "no-store")]),
                         b"")
    reply.headers["Access-Control-Allow-Origin"] = "*"
    # Not a CORS-safelisted response header: without this the page cannot read it.
    reply.headers["Access-Control-Expose-Headers"] = "Retry-After"
    return reply


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
