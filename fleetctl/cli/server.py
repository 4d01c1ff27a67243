"""``fleetctl server``: run the relay server from a ``server.yaml``."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import typer

from fleetctl.errors import ConfigError

CONFIG_HELP = """Run the relay server (WebSocket + HTTP on one port).

\b
server.yaml (relative paths are relative to the file):
  listen_host: 0.0.0.0          address to bind
  listen_port: 8080             TCP port (0 = any free port)
  auth_map: auth.yaml           identities (ip | cidr | token_sha256) and
                                rules {topic: RE2, op: send|receive|both}
  database: fleet.db            SQLite robot registry (survives restarts)
  tls_cert: null                PEM cert and key for wss://; both or neither
  tls_key: null
  trusted_proxies: []           IPs/CIDRs whose X-Forwarded-For is believed
  no_drop_topics: []            RE2 full-match topics always delivered in order
  limits:
    max_frame_bytes: 16777216          larger frames close with 1009
    max_subscriptions_per_connection: 256
    outbound_queue_bytes: 8388608      per connection, all topics
    outbound_no_drop_messages: 1024    per connection no_drop FIFO
    robot_offline_after_s: 5.0
    max_malformed_in_row: 10           then close with 1007
    auth_timeout_s: 10.0               for the {"token": ...} frame
    session_expiry_s: 3600.0           named sessions offline this long are dropped
    session_mailbox_messages: 10000    no_drop frames kept per offline session
    session_mailbox_bytes: 16777216
    max_sessions_per_identity: 64

\b
HTTP: GET /healthz, GET /metrics (Prometheus), GET /robots (JSON).
Stops gracefully on SIGTERM / SIGINT. See docs/server.md.
"""


def register(app: typer.Typer) -> None:
    """Add the ``server`` command to *app*."""

    @app.command("server", help=CONFIG_HELP)
    def server(
        config: Path = typer.Option(..., "--config", "-c", help="Path of server.yaml."),
        log_level: str = typer.Option("info", "--log-level", help="debug, info, warning."),
    ) -> None:
        from fleetctl.server.app import RelayServer, run_server
        from fleetctl.server.config import load_server_config

        level = getattr(logging, log_level.upper(), None)
        if not isinstance(level, int):
            raise ConfigError(f"--log-level: unknown level {log_level!r}")
        logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s %(message)s")
        cfg = load_server_config(config)

        def ready(srv: RelayServer) -> None:
            typer.echo(f"fleetctl server listening on {srv.url}", err=True)

        try:
            asyncio.run(run_server(cfg, ready=ready))
        except OSError as exc:
            raise ConfigError(
                f"{config}: cannot listen on {cfg.listen_host}:{cfg.listen_port}: {exc.strerror}"
            ) from None
