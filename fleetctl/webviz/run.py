"""Run the webviz HTTP server in the foreground (what ``fleetctl webviz`` and the webviz
image run) until SIGINT/SIGTERM."""

from __future__ import annotations

import logging
import signal
import threading
from types import FrameType

from fleetctl.errors import ConfigError, EnvironmentMissing
from fleetctl.webviz.config import WebvizConfig
from fleetctl.webviz.httpserver import BackgroundWebviz
from fleetctl.webviz.layouts import LayoutCache
from fleetctl.webviz.vendor import missing_vendor_libs
from fleetctl.wire.errors import WireError
from fleetctl.wire.registry import TypeRegistry

log = logging.getLogger("fleetctl.webviz")


def start_webviz(config: WebvizConfig, registry: TypeRegistry | None = None) -> BackgroundWebviz:
    """Bind and start serving in a background thread.

    Args:
        config: What to serve and where.
        registry: Type registry for ``/types/``; if None, :meth:`TypeRegistry.default`
            plus ``config.msg_types``.

    Returns:
        The running server (call ``stop()``).

    Raises:
        EnvironmentMissing: the static files are missing or the address cannot be bound.
        ConfigError: ``config.msg_types`` cannot be registered (the message says which).
    """
    if not (config.static_dir / "index.html").is_file():
        raise EnvironmentMissing(
            f"{config.static_dir}/index.html not found: the package is incomplete"
        )
    for line in missing_vendor_libs(config.vendor_dir):
        log.warning("webviz: %s", line)
    if registry is None:
        try:
            registry = TypeRegistry.default_with(config.msg_types)
        except WireError as exc:
            first_line = str(exc).splitlines()[0]
            raise ConfigError(f"the fleet's own message types: {first_line}") from None
    cache = LayoutCache(registry, config.max_layout_cache_types)
    try:
        server = BackgroundWebviz(config, cache)
    except OSError as exc:
        where = f"{config.listen_host}:{config.listen_port}"
        raise EnvironmentMissing(f"cannot listen on {where}: {exc.strerror}") from exc
    return server.start()


def run_webviz(config: WebvizConfig) -> None:
    """Serve until SIGINT or SIGTERM."""
    done = threading.Event()

    def stop(_sig: int, _frame: FrameType | None) -> None:
        done.set()

    # Before the "serving" line: a SIGTERM sent as soon as it is read (a supervisor, a
    # test) killed the process (exit -15) instead of stopping it.
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    if config.msg_types:
        names = [name for name, _ in config.msg_types]
        more = f", ... ({len(names)} in all)" if len(names) > 5 else ""
        log.info("webviz: the fleet's own message types too: %s%s", ", ".join(names[:5]), more)
    server = start_webviz(config)
    log.info(
        "webviz: serving %s (fleet server %s)",
        server.url,
        config.server_url or "ws://<the page's host>:8080/",
    )
    done.wait()
    server.stop()
