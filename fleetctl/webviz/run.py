"""Run the webviz HTTP server in the foreground (what ``fleetctl webviz`` and the webviz
image run) until SIGINT/SIGTERM."""

from __future__ import annotations

import logging
import signal
import threading
from types import FrameType

from fleetctl.errors import EnvironmentMissing
from fleetctl.webviz.config import WebvizConfig
from fleetctl.webviz.httpserver import BackgroundWebviz
from fleetctl.webviz.layouts import LayoutCache
from fleetctl.webviz.vendor import missing_vendor_libs
from fleetctl.wire.registry import TypeRegistry

log = logging.getLogger("fleetctl.webviz")


def start_webviz(config: WebvizConfig, registry: TypeRegistry | None = None) -> BackgroundWebviz:
    """Bind and start serving in a background thread.

    Args:
        config: What to serve and where.
        registry: Type registry for ``/types/``; :meth:`TypeRegistry.default` if None.

    Returns:
        The running server (call ``stop()``).

    Raises:
        EnvironmentMissing: the static files are missing or the address cannot be bound.
    """
    if not (config.static_dir / "index.html").is_file():
        raise EnvironmentMissing(
            f"{config.static_dir}/index.html not found: the package is incomplete"
        )
    for line in missing_vendor_libs(config.vendor_dir):
        log.warning("webviz: %s", line)
    cache = LayoutCache(registry or TypeRegistry.default(), config.max_layout_cache_types)
    try:
        server = BackgroundWebviz(config, cache)
    except OSError as exc:
        where = f"{config.listen_host}:{config.listen_port}"
        raise EnvironmentMissing(f"cannot listen on {where}: {exc.strerror}") from exc
    return server.start()


def run_webviz(config: WebvizConfig) -> None:
    """Serve until SIGINT or SIGTERM."""
    server = start_webviz(config)
    log.info(
        "webviz: serving %s (fleet server %s)",
        server.url,
        config.server_url or "ws://<the page's host>:8080/",
    )
    done = threading.Event()

    def stop(_sig: int, _frame: FrameType | None) -> None:
        done.set()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    done.wait()
    server.stop()
