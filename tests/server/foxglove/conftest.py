"""Fixtures of the Foxglove tests: a relay with a TLS web listener (tickets need TLS),
robots on its plain relay port, LaserScan messages made with rosbags' own types."""

from __future__ import annotations

import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from fleetctl.server.app import RelayServer
from fleetctl.server.config import WebConfig
from fleetctl.wire.codec import default_codec
from tests.server.certs import self_signed

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
REFERENCE = get_typestore(Stores.ROS2_JAZZY)  # rosbags' own definitions and deserializer


@pytest.fixture
def web_config(tmp_path: Path) -> WebConfig:
    cert, key = self_signed(tmp_path / "tls")
    vendor = tmp_path / "vendor"
    vendor.mkdir()
    return WebConfig(tls_cert=cert, tls_key=key, listen_host="127.0.0.1", listen_port=0,
                     vendor_dir=vendor)


@pytest.fixture
async def fx_server(make_server: Callable[..., RelayServer],
                    web_config: WebConfig) -> AsyncIterator[RelayServer]:
    async with make_server(web=web_config) as srv:
        yield srv


def scan(seq: int, n: int = 360) -> Any:
    """A LaserScan built from rosbags' Jazzy classes (not the project's encoder)."""
    t = REFERENCE.types
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=seq, nanosec=123), frame_id="laser")
    ranges = np.linspace(0.5, 10.0, n, dtype=np.float32) + np.float32(seq)
    return t[SCAN_TYPE](header=header, angle_min=-1.5, angle_max=1.5, angle_increment=0.01,
                        time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=30.0,
                        ranges=ranges, intensities=np.zeros(n, dtype=np.float32))


def scan_frame(topic: str, seq: int, n: int = 360) -> bytes:
    """The fleet frame a robot sends for :func:`scan` (its wire encoding)."""
    codec = default_codec()
    cdr = REFERENCE.serialize_cdr(scan(seq, n), SCAN_TYPE)
    msg = codec.registry.typestore.deserialize_cdr(cdr, SCAN_TYPE)
    return codec.encode(msg, SCAN_TYPE, topic, seq=seq, publish_time_ns=time.time_ns())
