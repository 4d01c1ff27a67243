"""``fleetctl server``: run the relay server from a ``server.yaml``."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import typer

from fleetctl.errors import ConfigError, ExitCode, FleetError

CONFIG_HELP = """Run the relay server: WebSocket + HTTP, optionally the web page over HTTPS.

The WebSocket and HTTP share one port; the web page and its WebSocket
(wss://) take a second, HTTPS port when server.yaml has a `web` section.

\b
server.yaml (relative paths are relative to the file):
  listen_host: 0.0.0.0          address to bind, or a list of addresses
                                (e.g. [10.8.0.1, 127.0.0.1])
  listen_port: 8080             TCP port (0 = any free port)
  auth_map: auth.yaml           identities (ip | cidr | token_sha256) and
                                rules {topic: RE2, op: send|receive|both};
                                reloaded on change and on SIGHUP
  database: fleet.db            SQLite robot registry (survives restarts)
  tls_cert: null                PEM cert and key for wss://; both or neither
  tls_key: null
  trusted_proxies: []           IPs/CIDRs whose X-Forwarded-For is believed
  no_drop_topics: []            RE2 full-match topics always delivered
                                in order
  limits:
    max_frame_bytes: 16777216          larger frames close with 1009
    max_subscriptions_per_connection: 256
    outbound_queue_bytes: 8388608      per connection, all topics
    outbound_no_drop_messages: 1024    per connection no_drop FIFO
    robot_offline_after_s: 5.0
    max_malformed_in_row: 10           then close with 1007
    auth_timeout_s: 10.0               for the {"token": ...} frame
    session_expiry_s: 3600.0           named sessions offline this long
                                       are dropped
    session_mailbox_messages: 10000    no_drop frames kept per offline
                                       session
    session_mailbox_bytes: 16777216
    max_sessions_per_identity: 64
  web:                          optional: the web page and the relay on one
                                HTTPS origin (identity by token only)
    listen_host: 0.0.0.0        address, or a list of addresses
    listen_port: 8443           TCP port (0 = any free port)
    tls_cert: tls/cert.pem      required, PEM certificate (chain)
    tls_key: tls/key.pem        required, its unencrypted PEM private key
    vendor_dir: /usr/share/javascript   Debian libjs-three / libjs-leaflet
  recording:                    optional: MCAP files of matching frames
    directory: recordings       created at start
    rules: [{topic: RE2, identities: [NAME, ...]}]   identities omitted: any
    max_file_bytes: 268435456   rotate before a file passes it
    max_total_bytes: 10737418240   oldest closed files deleted past it
    max_age_s: null             delete closed files older than this
    queue_bytes: 67108864       frames waiting; past it: dropped, counted

\b
HTTP: GET /healthz, GET /metrics (Prometheus), GET /robots (JSON),
GET /recordings and /recordings/NAME (MCAP files whose every topic the
caller may receive); on the web port: the page (/, /config.json,
/types/..., /vendor/...) and /healthz.
auth.yaml: a changed file (checked every 0.25 s) or SIGHUP reloads it; an
invalid file is logged and the previous map stays. Connections whose
identities are gone are closed with 4403; the others keep their connection.
Stops gracefully on SIGTERM / SIGINT. See docs/server.md.
"""


def register(app: typer.Typer) -> None:
    """Add the ``server`` command to *app*."""

    @app.command("server", help=CONFIG_HELP)
    def server(
        config: Path = typer.Option(..., "--config", "-c", help="Path of server.yaml."),
        log_level: str = typer.Option("info", "--log-level", help="debug, info, warning or error."),
    ) -> None:
        from fleetctl.server.app import ListenError, RelayServer, run_server
        from fleetctl.server.cluster.config import ClusterStartError
        from fleetctl.server.config import load_server_config

        level = getattr(logging, log_level.upper(), None)
        if not isinstance(level, int):
            # A usage error (2), as the client's: was 3, the code of a bad config file.
            raise FleetError(f"--log-level: unknown level {log_level!r}; use one of debug, "
                             "info, warning, error", exit_code=ExitCode.USAGE)
        logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s %(message)s")
        cfg = load_server_config(config)

        def ready(srv: RelayServer) -> None:
            typer.echo(f"fleetctl server listening on {srv.url}", err=True)
            if srv.web_url is not None:
                typer.echo(f"fleetctl server web page on {srv.web_url}", err=True)

        try:
            asyncio.run(run_server(cfg, ready=ready))
        except (ListenError, ClusterStartError) as exc:
            raise ConfigError(f"{config}: {exc}") from None
