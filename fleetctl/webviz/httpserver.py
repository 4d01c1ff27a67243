"""The routes of the web visualizer page, and the small stdlib HTTP server of
``fleetctl webviz`` that answers them.

Routes (:meth:`WebPage.lookup`, shared with the relay's web listener):
    ``/``                 the page (``static/index.html``)
    ``/config.json``      ``{"server_url": ...}`` for the page (``null``: its own origin)
    ``/types/<T>.json``   FlatBuffer layout of ROS type ``T`` (see :mod:`.layouts`)
    ``/vendor/<lib>/...`` Debian's three.js / Leaflet (see :mod:`.vendor`)
    anything else         a file under ``static/``

Every path is resolved and must stay inside its root directory; anything else is a 404.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from fleetctl.webviz.config import WebvizConfig
from fleetctl.webviz.layouts import LayoutError
from fleetctl.webviz.vendor import VENDOR_LIBS

log = logging.getLogger(__name__)

DEFAULT_RELAY_PORT = 8080
"""The relay's default port: where a page served without ``--server-url`` looks for it."""

LayoutSource = Callable[[str], bytes]
"""Returns the JSON layout of a ROS type name; raises LayoutError when unknown."""

_CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",  # ES modules are refused without a JS type
    ".mjs": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".json": "application/json",
    ".map": "application/json",
    ".png": "image/png",
    ".svg": "image/svg+xml",
}


def _inside(root: Path, rel: str) -> Path | None:
    """The file ``root/rel`` if it exists and does not escape ``root``, else None."""
    try:
        path = (root / rel).resolve()
    except (OSError, ValueError):
        return None
    if not path.is_relative_to(root.resolve()) or not path.is_file():
        return None
    return path


@dataclass(frozen=True)
class PageReply:
    """One answer of :meth:`WebPage.lookup`.

    Attributes:
        status: HTTP status.
        body: The body bytes.
        content_type: ``Content-Type`` header value.
        error: Why, for a non-200 status (also in the JSON body), else ``None``.
        shared: Any origin may read it (``Access-Control-Allow-Origin: *``): the type
            layouts, public schema data that the page of another relay replica loads
            from the replica it is connected to (docs/webviz.md, "Replicas").
    """

    status: HTTPStatus
    body: bytes
    content_type: str
    error: str | None = None
    shared: bool = False


class WebPage:
    """The page's routes, whatever HTTP server answers them (the stdlib server of
    ``fleetctl webviz`` or the relay's web listener).

    Files are read on each request (they are small, and the page revalidates them);
    type layouts come from *layouts*, which caches them.

    Args:
        static_dir: The page's files.
        vendor_dir: Directory holding ``three/`` and ``leaflet/``.
        layouts: Source of ``/types/<T>.json`` bodies.
    """

    def __init__(self, static_dir: Path, vendor_dir: Path, layouts: LayoutSource) -> None:
        self.static_dir = static_dir
        self.vendor_dir = vendor_dir
        self.layouts = layouts

    def lookup(self, target: str, server_url: str | None,
               replica_ports: tuple[int, ...] = ()) -> PageReply:
        """Answer ``GET target``.

        Args:
            target: The request target (path, maybe with a query), percent-encoded.
            server_url: What ``/config.json`` tells the page; ``None`` means the page's
                own origin (``wss://`` under https).
            replica_ports: The relay replicas' HTTPS ports on the page's host, for the
                page's failover (``/config.json``; empty: no replicas).

        Returns:
            The reply: 200 with the file, or 404 with a JSON ``{"error": ...}`` body.
        """
        path = unquote(urlsplit(target).path)
        if path in ("/", "/index.html"):
            return self._file(self.static_dir / "index.html")
        if path == "/config.json":
            config: dict[str, object] = {"server_url": server_url}
            if replica_ports:
                config["replica_ports"] = list(replica_ports)
            return _reply(json.dumps(config).encode(), ".json")
        if path.startswith("/types/") and path.endswith(".json"):
            return self._layout(path[len("/types/") : -len(".json")])
        if path.startswith("/vendor/"):
            return self._vendor(path[len("/vendor/") :])
        found = _inside(self.static_dir, path.lstrip("/"))
        if found is None:
            return _not_found(f"no such file: {path}")
        return self._file(found)

    def _layout(self, type_name: str) -> PageReply:
        try:
            return dataclasses.replace(_reply(self.layouts(type_name), ".json"), shared=True)
        except LayoutError as exc:
            return _not_found(str(exc))

    def _vendor(self, rel: str) -> PageReply:
        lib, _, rest = rel.partition("/")
        if lib not in {v.name for v in VENDOR_LIBS}:
            return _not_found(f"no vendored library {lib!r}")
        found = _inside(self.vendor_dir / lib, rest)
        if found is None:
            pkg = next(v.debian_package for v in VENDOR_LIBS if v.name == lib)
            return _not_found(f"{lib}/{rest} is not installed (Debian package {pkg})")
        return self._file(found)

    @staticmethod
    def _file(path: Path) -> PageReply:
        try:
            body = path.read_bytes()
        except OSError as exc:
            return _not_found(f"cannot read {path.name}: {exc.strerror}")
        return _reply(body, path.suffix)


def _reply(body: bytes, suffix: str) -> PageReply:
    content_type = _CONTENT_TYPES.get(suffix, "application/octet-stream")
    return PageReply(HTTPStatus.OK, body, content_type)


def _not_found(message: str) -> PageReply:
    body = json.dumps({"error": message}).encode()
    return PageReply(HTTPStatus.NOT_FOUND, body, _CONTENT_TYPES[".json"], message)


_HOST_RE = re.compile(r"[A-Za-z0-9.-]+|\[[0-9A-Fa-f:.]+\]")


def default_server_url(host_header: str | None, forwarded_proto: str | None,
                       fallback_host: str) -> str:
    """The relay URL a page served without ``--server-url`` connects to.

    ``ws://<hostname the browser used>:8080/``, ``wss://`` when a TLS proxy in front says
    ``X-Forwarded-Proto: https`` (what the page itself chose before this was explicit).

    Args:
        host_header: The request's ``Host`` header, if any.
        forwarded_proto: The ``X-Forwarded-Proto`` header, if any.
        fallback_host: Used when the header is missing or not a plain host name.
    """
    host = (host_header or "").strip()
    if host.startswith("["):
        host = host.partition("]")[0] + "]"
    else:
        host = host.rpartition(":")[0] if host.count(":") == 1 else host
    if not _HOST_RE.fullmatch(host):
        host = fallback_host
    scheme = "wss" if (forwarded_proto or "").strip().lower() == "https" else "ws"
    return f"{scheme}://{host}:{DEFAULT_RELAY_PORT}/"


# Why: each connection holds a thread; a silent client must not hold one for long, and
# many clients must not make many threads (the page makes a few dozen small requests).
REQUEST_TIMEOUT_S = 10.0
MAX_CONNECTION_THREADS = 64


class _Handler(BaseHTTPRequestHandler):
    server: WebvizHTTPServer
    server_version = "fleetctl-webviz"
    timeout = REQUEST_TIMEOUT_S  # socket timeout: a silent or slow client is dropped

    def log_message(self, format: str, *args: object) -> None:
        log.debug("%s " + format, self.address_string(), *args)

    def do_GET(self) -> None:
        url = self.server.config.server_url or default_server_url(
            self.headers.get("Host"), self.headers.get("X-Forwarded-Proto"),
            self.server.local_host(),
        )
        reply = self.server.page.lookup(self.path, url)
        if reply.error is not None:
            log.info("webviz: %s %s: %s", reply.status.value, self.path, reply.error)
        self.send_response(reply.status)
        self.send_header("Content-Type", reply.content_type)
        if reply.shared:
            self.send_header("Access-Control-Allow-Origin", "*")
        self.send_header("Content-Length", str(len(reply.body)))
        # The page is small and changes with the package: always revalidate.
        self.send_header("Cache-Control", "no-cache")
        self.end_headers()
        self.wfile.write(reply.body)


class WebvizHTTPServer(ThreadingHTTPServer):
    """Serves the page; one thread per connection, at most :attr:`max_threads` at once
    (one more connection is closed at accept, counted in :attr:`refused`), each dropped
    after :data:`REQUEST_TIMEOUT_S` of silence."""

    daemon_threads = True

    def __init__(self, config: WebvizConfig, layouts: LayoutSource,
                 max_threads: int = MAX_CONNECTION_THREADS) -> None:
        """Bind the listening socket (port 0 picks a free port).

        Args:
            config: What to serve and where.
            layouts: Source of ``/types/<T>.json`` bodies.
            max_threads: Connections served at once.

        Raises:
            OSError: the address cannot be bound.
        """
        self.config = config
        self.page = WebPage(config.static_dir, config.vendor_dir, layouts)
        self.max_threads = max_threads
        self._slots = threading.BoundedSemaphore(max_threads)
        self.refused = 0
        super().__init__((config.listen_host, config.listen_port), _Handler)

    def process_request(self, request: Any, client_address: Any) -> None:
        """Serve *request* in a thread if one is free, else close it at once."""
        if not self._slots.acquire(blocking=False):
            self.refused += 1
            if self.refused % 1000 == 1:
                log.warning("webviz: %d connections open, refusing more (%d refused so far)",
                            self.max_threads, self.refused)
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        """Serve one connection, then give its slot back."""
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

    @property
    def port(self) -> int:
        """The bound TCP port."""
        return int(self.server_address[1])

    def local_host(self) -> str:
        """The bound address as a URL host (``127.0.0.1`` for a wildcard bind)."""
        host = str(self.server_address[0])
        if host in ("0.0.0.0", "", "::"):
            return "127.0.0.1"
        return f"[{host}]" if ":" in host else host


class BackgroundWebviz:
    """A :class:`WebvizHTTPServer` running in a thread (tests, ``fleetctl demo``)."""

    def __init__(self, config: WebvizConfig, layouts: LayoutSource) -> None:
        """Bind now; serving starts with :meth:`start`."""
        self.server = WebvizHTTPServer(config, layouts)
        self._thread = threading.Thread(
            target=self.server.serve_forever, name="webviz", daemon=True
        )

    @property
    def url(self) -> str:
        """Base URL of the page, e.g. ``http://127.0.0.1:40123/``."""
        host = self.server.config.listen_host
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.server.port}/"

    def start(self) -> BackgroundWebviz:
        """Start serving; returns self."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the socket (waits for the serving thread)."""
        self.server.shutdown()
        self.server.server_close()
        self._thread.join()

    def __enter__(self) -> BackgroundWebviz:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
