"""The relay's web listener: the page of ``fleetctl webviz`` and the relay's WebSocket on
one HTTPS origin (so a browser needs one certificate, one port and no mixed content).

The page's routes are :meth:`fleetctl.webviz.httpserver.WebPage.lookup`, the same function
the stdlib ``fleetctl webviz`` server answers with; here ``/config.json`` says
``{"server_url": null}``: the page connects back to its own origin. The relay's event loop
answers these requests: files are small and read synchronously, type layouts are cached
(:class:`~fleetctl.webviz.layouts.LayoutCache`).
"""

from __future__ import annotations

import http
import logging

from websockets.http11 import Request, Response

from fleetctl.server import endpoints
from fleetctl.server.config import WebConfig
from fleetctl.webviz.config import STATIC_DIR
from fleetctl.webviz.httpserver import WebPage
from fleetctl.webviz.layouts import LayoutCache
from fleetctl.webviz.vendor import missing_vendor_libs
from fleetctl.wire.registry import TypeRegistry

log = logging.getLogger("fleetctl.server")

# Why 256: the page asks for the layouts of the types it shows, a few dozen at most.
MAX_LAYOUT_CACHE_TYPES = 256


def web_page(config: WebConfig, registry: TypeRegistry | None = None) -> WebPage:
    """Build the page's routes for the web listener; warn about missing vendored libraries.

    Args:
        config: The web listener's config.
        registry: The types whose layouts the page gets (the server's, with the fleet's
            own message types); ``None``: :meth:`TypeRegistry.default`.
    """
    for line in missing_vendor_libs(config.vendor_dir):
        log.warning("web listener: %s", line)
    layouts = LayoutCache(registry or TypeRegistry.default(), MAX_LAYOUT_CACHE_TYPES)
    return WebPage(STATIC_DIR, config.vendor_dir, layouts)


def page_response(page: WebPage, request: Request,
                  replica_ports: tuple[int, ...] = ()) -> Response:
    """Answer a plain GET on the web listener: ``/healthz`` or one of the page's routes
    (``/config.json`` lists *replica_ports*, the page's failover targets)."""
    if request.path.split("?", 1)[0] == "/healthz":
        return endpoints.text(http.HTTPStatus.OK, "ok\n")
    reply = page.lookup(request.path, None, replica_ports)
    return endpoints.response(reply.status, reply.body, reply.content_type,
                              cache_control="no-cache", shared=reply.shared)


class QuietSuccess(logging.Filter):
    """Drop websockets' ``connection rejected (2xx ...)`` and ``(429 ...)`` lines.

    websockets logs every response that is not a WebSocket upgrade as a rejection, at
    INFO: a health check every 5 s, each file of the page. Those are answers, not
    rejections; real ones (401, 403, 404, ...) stay in the log. A 429 (an address over
    its failed-login budget, :mod:`fleetctl.server.loginbudget`) has its own sampled
    line: a script retrying flat out would otherwise write one line per attempt.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        """Return ``False`` for a successful plain-HTTP answer or a 429."""
        if record.msg != "connection rejected (%d %s)" or not isinstance(record.args, tuple):
            return True
        status = record.args[0] if record.args else None
        return not (isinstance(status, int) and (200 <= status < 300 or status == 429))
