"""The small HTTP server of the web visualizer (stdlib only).

Routes:
    ``/``                 the page (``static/index.html``)
    ``/config.json``      ``{"server_url": ...}`` for the page
    ``/types/<T>.json``   FlatBuffer layout of ROS type ``T`` (see :mod:`.layouts`)
    ``/vendor/<lib>/...`` Debian's three.js / Leaflet (see :mod:`.vendor`)
    anything else         a file under ``static/``

Every path is resolved and must stay inside its root directory; anything else is a 404.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlsplit

from fleetctl.webviz.config import WebvizConfig
from fleetctl.webviz.layouts import LayoutError
from fleetctl.webviz.vendor import VENDOR_LIBS

log = logging.getLogger(__name__)

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


class _Handler(BaseHTTPRequestHandler):
    server: WebvizHTTPServer
    server_version = "fleetctl-webviz"

    def log_message(self, format: str, *args: object) -> None:
        log.debug("%s " + format, self.address_string(), *args)

    def do_GET(self) -> None:
        path = unquote(urlsplit(self.path).path)
        if path in ("/", "/index.html"):
            return self._file(self.server.config.static_dir / "index.html")
        if path == "/config.json":
            return self._bytes(self.server.config_json(), ".json")
        if path.startswith("/types/") and path.endswith(".json"):
            return self._layout(path[len("/types/") : -len(".json")])
        if path.startswith("/vendor/"):
            return self._vendor(path[len("/vendor/") :])
        found = _inside(self.server.config.static_dir, path.lstrip("/"))
        if found is None:
            return self._error(HTTPStatus.NOT_FOUND, f"no such file: {path}")
        return self._file(found)

    def _layout(self, type_name: str) -> None:
        try:
            body = self.server.layouts(type_name)
        except LayoutError as exc:
            return self._error(HTTPStatus.NOT_FOUND, str(exc))
        self._bytes(body, ".json")

    def _vendor(self, rel: str) -> None:
        lib, _, rest = rel.partition("/")
        if lib not in {v.name for v in VENDOR_LIBS}:
            return self._error(HTTPStatus.NOT_FOUND, f"no vendored library {lib!r}")
        found = _inside(self.server.config.vendor_dir / lib, rest)
        if found is None:
            pkg = next(v.debian_package for v in VENDOR_LIBS if v.name == lib)
            msg = f"{lib}/{rest} is not installed (Debian package {pkg})"
            return self._error(HTTPStatus.NOT_FOUND, msg)
        self._file(found)

    def _file(self, path: Path) -> None:
        try:
            body = path.read_bytes()
        except OSError as exc:
            return self._error(HTTPStatus.NOT_FOUND, f"cannot read {path.name}: {exc.strerror}")
        self._bytes(body, path.suffix)

    def _bytes(self, body: bytes, suffix: str, status: HTTPStatus = HTTPStatus.OK) -> None:
        self.send_response(status)
        self.send_header("Content-Type", _CONTENT_TYPES.get(suffix, "application/octet-stream"))
        self.send_header("Content-Length", str(len(body)))
        # The page is small and changes with the package: always revalidate.
        self.send_header("Cache-Control", "no-cache")
        self.end_headers()
        self.wfile.write(body)

    def _error(self, status: HTTPStatus, message: str) -> None:
        log.info("webviz: %s %s: %s", status.value, self.path, message)
        self._bytes(json.dumps({"error": message}).encode(), ".json", status)


class WebvizHTTPServer(ThreadingHTTPServer):
    """Serves the page; one thread per request (the page makes few, small requests)."""

    daemon_threads = True

    def __init__(self, config: WebvizConfig, layouts: LayoutSource) -> None:
        """Bind the listening socket (port 0 picks a free port).

        Args:
            config: What to serve and where.
            layouts: Source of ``/types/<T>.json`` bodies.

        Raises:
            OSError: the address cannot be bound.
        """
        self.config = config
        self.layouts = layouts
        super().__init__((config.listen_host, config.listen_port), _Handler)

    @property
    def port(self) -> int:
        """The bound TCP port."""
        return int(self.server_address[1])

    def config_json(self) -> bytes:
        """The body of ``/config.json``."""
        return json.dumps({"server_url": self.config.server_url}).encode()


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
