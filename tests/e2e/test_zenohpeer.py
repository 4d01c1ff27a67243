"""The zenoh baseline's configs work with real zenoh: a router, a publisher, a subscriber
on loopback, under both settings."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from fleetctl.e2e import zenohpeer
from fleetctl.errors import FleetError

zenoh = pytest.importorskip("zenoh")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@pytest.mark.parametrize("settings", zenohpeer.SETTINGS)
def test_a_put_reaches_a_subscriber_through_the_router(settings: str) -> None:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    got: list[bytes] = []
    arrived = threading.Event()

    def on_sample(sample: object) -> None:
        got.append(sample.payload.to_bytes())  # type: ignore[attr-defined]
        arrived.set()

    with zenoh.open(zenohpeer.session_config(settings, "router", listen=endpoint)), \
            zenoh.open(zenohpeer.session_config(settings, "client", connect=endpoint)) as sub, \
            zenoh.open(zenohpeer.session_config(settings, "client", connect=endpoint)) as pub:
        sub.declare_subscriber("robot1/**", on_sample)
        publisher = pub.declare_publisher(zenohpeer.key_of("/pose"),
                                          **zenohpeer.publisher_options(settings, "/pose"))
        deadline = time.monotonic() + 10
        while not arrived.is_set() and time.monotonic() < deadline:
            publisher.put(b"cdr")  # until the subscription has propagated
            arrived.wait(0.1)
    assert got and got[0] == b"cdr"


def test_best_settings_are_the_documented_ones() -> None:
    best = zenohpeer.session_config("best", "client", connect="tcp/127.0.0.1:1")
    assert '"lease":3000' in best.get_json("transport/link/tx").replace(" ", "")
    assert best.get_json("transport/link/tcp/so_sndbuf") == "8192"
    pose = zenohpeer.publisher_options("best", "/pose")
    scan = zenohpeer.publisher_options("best", "/scan")
    assert pose["priority"] == zenoh.Priority.INTERACTIVE_HIGH
    assert scan["priority"] == zenoh.Priority.DATA
    assert pose["congestion_control"] == zenoh.CongestionControl.DROP and pose["express"]
    default = zenohpeer.publisher_options("default", "/pose")
    assert default["congestion_control"] == zenoh.CongestionControl.BLOCK
    with pytest.raises(FleetError, match="zenoh settings"):
        zenohpeer.session_config("fast", "client")
