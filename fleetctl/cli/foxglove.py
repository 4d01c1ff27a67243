"""``fleetctl foxglove-url``: a one-time URL to open the fleet in Foxglove or Lichtblick.

Asks the server (``GET /foxglove/ticket`` with a Bearer token, over TLS) for a ticket and
prints ``wss://host:port/?ticket=...``, which Foxglove's "Open connection" -> "Foxglove
WebSocket" takes as is. The ticket works once, within the validity the server says
(60 s by default), as the identity of the token (docs/foxglove.md).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import typer

from fleetctl.cli.output import OutputFormat, emit, output_option, progress_line
from fleetctl.cli.recordings import Remote
from fleetctl.cli.tokenfile import read_token_file
from fleetctl.errors import ConfigError, FleetError

TICKET_PATH = "/foxglove/ticket"


@dataclass(frozen=True)
class FoxgloveUrl:
    """A URL to paste into Foxglove.

    Attributes:
        url: ``wss://host:port/?ticket=...``.
        expires_in_s: Seconds the ticket stays valid (it works once).
    """

    url: str
    expires_in_s: float


def foxglove_url(remote: Remote) -> FoxgloveUrl:
    """Fetch a ticket from *remote* and build the URL.

    Raises:
        ConfigError: The server URL is not ``https://`` or ``wss://``.
        FleetError: The server cannot be reached, refuses, or answers nonsense.
    """
    if not remote.url.startswith(("https://", "wss://")):
        raise ConfigError(f"--server {remote.url}: tickets are issued over TLS only: use "
                          "an https:// or wss:// URL (the web listener)")
    _status, _headers, body = remote.get(TICKET_PATH)
    try:
        answer = json.loads(body)
        ticket, expires = str(answer["ticket"]), float(answer["expires_in_s"])
    except (ValueError, KeyError, TypeError):
        raise FleetError(f"{remote.url}: GET {TICKET_PATH}: not a ticket answer") from None
    url = answer.get("url") or _ws_url(remote.url, ticket)
    return FoxgloveUrl(str(url), expires)


def _ws_url(server: str, ticket: str) -> str:
    base = server.rstrip("/").replace("https://", "wss://", 1)
    return f"{base}/?ticket={ticket}"


_SERVER = typer.Option(..., "--server", "-s", help="https:// or wss:// URL of the server's "
                       "TLS port (the web listener).")
_TOKEN = typer.Option(..., "--token-file", help="File holding your Bearer token.")
_CA = typer.Option(None, "--ca-file", help="CA bundle to verify the server with.")


def register(app: typer.Typer) -> None:
    """Add ``foxglove-url`` to *app*."""

    @app.command("foxglove-url")
    def foxglove_url_command(server: str = _SERVER, token_file: Path = _TOKEN,
                             ca_file: Path | None = _CA,
                             output: OutputFormat = output_option()) -> None:
        """Print a one-time URL for Foxglove / Lichtblick ("Open connection")."""
        result = foxglove_url(Remote(server, read_token_file(token_file), ca_file))
        # stdout is the URL alone (URL=$(fleetctl foxglove-url ...) works); the how-to
        # goes to stderr.
        emit(result, output, lambda: result.url)
        if output is not OutputFormat.JSON:
            progress_line(f"valid once, for {result.expires_in_s:.0f} s: paste it into "
                          "Foxglove or Lichtblick, Open connection -> Foxglove WebSocket")
