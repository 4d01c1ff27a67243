"""``fleetctl webviz``: serve the web visualizer."""

from __future__ import annotations

import logging
from pathlib import Path
from urllib.parse import urlsplit

import typer

from fleetctl.errors import ConfigError
from fleetctl.webviz.config import DEBIAN_JS_DIR, WebvizConfig
from fleetctl.webviz.run import run_webviz


def _check_url(url: str | None) -> str | None:
    if url is None:
        return None
    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018  (raises ValueError for a bad port)
    except ValueError:  # urllib: a bad IPv6 literal or port
        parts = urlsplit("")
    if parts.scheme not in ("ws", "wss") or not parts.hostname:
        raise ConfigError(f"--server-url {url!r}: expected ws://HOST:PORT/ or wss://HOST:PORT/")
    return url


def register(app: typer.Typer) -> None:
    """Add ``webviz`` to *app*."""

    @app.command()
    def webviz(
        server_url: str | None = typer.Option(
            None,
            "--server-url",
            help="Fleet server WebSocket URL the page connects to "
            "(default: ws://<the page's host>:8080/).",
        ),
        host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on."),
        port: int = typer.Option(
            8000, "--port", min=0, max=65535, help="TCP port (0: any free port)."
        ),
        vendor_dir: Path = typer.Option(
            DEBIAN_JS_DIR,
            "--vendor-dir",
            help="Directory with three/ and leaflet/ (Debian libjs-three, libjs-leaflet).",
        ),
        verbose: bool = typer.Option(False, "--verbose", "-v", help="Log every request."),
    ) -> None:
        """Serve the web visualizer (static page, config.json, type layouts)."""
        logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, format="%(message)s")
        config = WebvizConfig(
            listen_host=host,
            listen_port=port,
            server_url=_check_url(server_url),
            vendor_dir=vendor_dir,
        )
        run_webviz(config)
