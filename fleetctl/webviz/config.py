"""Configuration of the webviz HTTP server (``fleetctl webviz``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from fleetctl.webviz.layouts import MsgTypes

STATIC_DIR = Path(__file__).resolve().parent / "static"
"""The page's own files (index.html, ES modules, css), shipped as package data."""

DEBIAN_JS_DIR = Path("/usr/share/javascript")
"""Where Debian's libjs-* packages install browser libraries (three.js, Leaflet)."""


@dataclass(frozen=True)
class WebvizConfig:
    """What the webviz server serves and where it listens.

    Attributes:
        listen_host: Address to bind (``127.0.0.1`` serves this machine only).
        listen_port: TCP port; 0 picks a free one (tests).
        server_url: Fleet server WebSocket URL given to the page in ``config.json``; None
            gives ``ws://<the host the browser asked for>:8080/`` (``wss://`` behind a
            proxy that sends ``X-Forwarded-Proto: https``).
        vendor_dir: Directory holding ``three/`` and ``leaflet/`` (Debian's
            ``/usr/share/javascript`` or a copy made at image build).
        static_dir: The page's files.
        max_layout_cache_types: Type layouts kept in memory (least recently used evicted).
        msg_types: The fleet's own message types, ``(pkg/msg/Name, .msg text)`` pairs,
            served in ``/types/`` beside the default ones (``fleetctl webviz --fleet``).
    """

    listen_host: str = "127.0.0.1"
    listen_port: int = 8000
    server_url: str | None = None
    vendor_dir: Path = DEBIAN_JS_DIR
    static_dir: Path = STATIC_DIR
    max_layout_cache_types: int = 256
    msg_types: MsgTypes = ()
