"""``fleetctl webviz``: serve the web visualizer."""

from __future__ import annotations

import ipaddress
import logging
import re
import socket
from pathlib import Path
from urllib.parse import urlsplit

import typer

from fleetctl.cli.output import PORT_OR_ANY
from fleetctl.deploy.msgtypes import MSG_TYPES_DIR, load_msg_types
from fleetctl.errors import ConfigError
from fleetctl.webviz.config import DEBIAN_JS_DIR, WebvizConfig
from fleetctl.webviz.layouts import MsgTypes
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


# A DNS name: dot-separated labels of ASCII letters, digits and '-' (not at either end).
_LABEL = re.compile(r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?")


def _check_host(host: str, port: int) -> str:
    """Return *host* if it is an IP address, or a DNS name that resolves.

    Raises:
        ConfigError: (exit code 3, naming ``--host``) anything else; binding would fail
            later with exit code 5 as if the machine lacked something.
    """
    try:
        ipaddress.ip_address(host)
        return host
    except ValueError:
        pass
    labels = host.removesuffix(".").split(".")
    # All digits and not an IP address (1.2.3.999, 010.0.0.1, which the resolver would
    # read as octal): not a name either.
    if (len(host) > 253 or not all(_LABEL.fullmatch(label) for label in labels)
            or all(label.isdigit() for label in labels)):
        raise ConfigError(f"--host {host[:80]!r}: not an IP address or a host name "
                          "(e.g. 127.0.0.1, 0.0.0.0, :: or localhost)")
    try:
        socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (OSError, UnicodeError) as exc:
        raise ConfigError(f"--host {host!r}: cannot resolve it: "
                          f"{getattr(exc, 'strerror', None) or exc}") from None
    return host


def _fleet_msg_types(fleet: Path | None) -> MsgTypes:
    """The fleet's own message types, read as ``fleetctl render`` reads them
    (``FLEET/msg_types/PKG/msg/NAME.msg``); none without ``--fleet``.

    Raises:
        ConfigError: (exit code 3) *fleet* is not a directory, or a definition is bad (the
            message names the file).
    """
    if fleet is None:
        return ()
    if not fleet.is_dir():
        raise ConfigError(f"--fleet {str(fleet)!r}: not a directory (a fleet directory, "
                          f"whose {MSG_TYPES_DIR}/PKG/msg/NAME.msg the page decodes too)")
    texts = load_msg_types(fleet).texts
    if not texts:  # asked for, and none: say so rather than serve as if they were there
        logging.getLogger("fleetctl.webviz").warning(
            "webviz: %s has no %s/PKG/msg/NAME.msg: the standard message types only",
            fleet, MSG_TYPES_DIR)
    return texts


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
        host: str = typer.Option("127.0.0.1", "--host",
                                 help="Address to listen on: an IP address or a host name."),
        port: int = typer.Option(
            8000, "--port", parser=PORT_OR_ANY, help="TCP port (0: any free port)."
        ),
        vendor_dir: Path = typer.Option(
            DEBIAN_JS_DIR,
            "--vendor-dir",
            help="Directory with three/ and leaflet/ (Debian libjs-three, libjs-leaflet).",
        ),
        fleet: Path | None = typer.Option(
            None,
            "--fleet",
            "-f",
            help=f"Fleet directory: the page decodes its own message types too "
            f"({MSG_TYPES_DIR}/PKG/msg/NAME.msg, as fleetctl render reads them). "
            "Default: the standard types only.",
        ),
        verbose: bool = typer.Option(False, "--verbose", "-v", help="Log every request."),
    ) -> None:
        """Serve the web visualizer (static page, config.json, type layouts)."""
        logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, format="%(message)s")
        config = WebvizConfig(
            listen_host=_check_host(host, port),
            listen_port=port,
            server_url=_check_url(server_url),
            vendor_dir=vendor_dir,
            msg_types=_fleet_msg_types(fleet),
        )
        run_webviz(config)
