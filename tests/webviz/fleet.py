"""A real fleet for browser tests: the relay server on an ephemeral loopback port and
robots that are real WebSocket clients publishing real encoded frames.

Robots are identified by source address as on WireGuard: each binds its own loopback
address (127.0.0.2, 127.0.0.3, ...), the auth map names them by ``ip``; people use tokens.
Maps go out compressed, as a robot with ``compression:`` on its map topic sends them: r1 with
deflate (the page inflates it), the others with zstd (the page says it cannot).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import io
import itertools
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from PIL import Image
from websockets.asyncio.client import ClientConnection, connect

from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import load_auth_map
from fleetctl.server.config import ServerConfig
from fleetctl.wire.codec import Codec
from fleetctl.wire.compression import CompressionCodec, compress
from fleetctl.wire.control import encode_status, encode_subscription
from fleetctl.wire.registry import TypeRegistry
from tests.webviz.msgs import make
from tests.webviz.samples import cloud_values, header, pose_values, scan_values

OPERATOR_TOKEN = "operator-token-0123456789"
VIEWER_TOKEN = "viewer-token-9876543210"
R1_VIEWER_TOKEN = "r1-viewer-token-5555555555"  # a user scoped to r1 (add-user --robots r1)
PUBLISH_PERIOD_S = 0.1  # the robots' sensor pacing (a rate, not synchronization)
RECEIVED_QUEUE = 64  # frames a robot keeps for the test to inspect; beyond: dropped, counted


def _sha(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def write_auth_map(path: Path, robots: dict[str, str]) -> Path:
    """Auth map: each robot by IP; an operator who may command; a viewer who may not."""
    idents: list[dict[str, Any]] = [
        {
            "name": name,
            "ip": ip,
            "rules": [
                {"topic": f"/{name}/.*", "op": "send"},
                {"topic": f"/{name}/(goal_pose|initialpose)", "op": "receive"},
            ],
        }
        for name, ip in robots.items()
    ]
    idents.append(
        {
            "name": "operator",
            "token_sha256": _sha(OPERATOR_TOKEN),
            "rules": [
                {"topic": ".*", "op": "receive"},
                {"topic": "/[^/]+/(goal_pose|initialpose)", "op": "send"},
            ],
        }
    )
    idents.append(
        {
            "name": "viewer",
            "token_sha256": _sha(VIEWER_TOKEN),
            "rules": [
                {"topic": ".*", "op": "receive"},
            ],
        }
    )
    idents.append(
        {
            "name": "r1-viewer",
            "token_sha256": _sha(R1_VIEWER_TOKEN),
            "rules": [{"topic": "/r1/.*", "op": "receive"}],
        }
    )
    path.write_text(yaml.safe_dump({"version": 1, "identities": idents}))
    return path


def jpeg_bytes(width: int = 160, height: int = 120) -> bytes:
    """A real JPEG: a colour gradient (mostly far from the panel background)."""
    x = np.linspace(0, 255, width, dtype=np.uint8)
    rgb = np.zeros((height, width, 3), dtype=np.uint8)
    rgb[..., 0] = x
    rgb[..., 1] = 200
    rgb[..., 2] = x[::-1]
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=85)
    return buf.getvalue()


@dataclass
class RobotConnection:
    """A robot's WebSocket connection to the relay: connects (from its own address), keeps
    what it receives in a bounded queue (overflow counted), closes."""

    name: str
    ip: str
    url: str
    codec: Codec
    received: asyncio.Queue[bytes] = field(default_factory=lambda: asyncio.Queue(RECEIVED_QUEUE))
    dropped: int = 0
    ws: ClientConnection | None = None
    tasks: list[asyncio.Task[None]] = field(default_factory=list)

    async def connect(self) -> ClientConnection:
        """Connect, wait for the server's welcome, start keeping what arrives."""
        self.ws = await connect(self.url, local_addr=(self.ip, 0), max_size=None)
        welcome = json.loads(await asyncio.wait_for(self.ws.recv(), 10))
        assert welcome["type"] == "welcome", welcome
        self.tasks.append(asyncio.create_task(self._read()))
        return self.ws

    async def stop(self) -> None:
        for t in self.tasks:
            t.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await t
        if self.ws is not None:
            await self.ws.close()

    async def _read(self) -> None:
        assert self.ws is not None
        async for frame in self.ws:
            if isinstance(frame, bytes):
                try:
                    self.received.put_nowait(frame)
                except asyncio.QueueFull:
                    self.dropped += 1


@dataclass
class WsRobot(RobotConnection):
    """One simulated robot as a WebSocket client of the relay."""

    async def start(self) -> None:
        ws = await self.connect()
        await ws.send(
            encode_subscription(f"/{self.name}/(goal_pose|initialpose)", codec=self.codec)
        )
        self.tasks.append(asyncio.create_task(self._publish()))

    def _frames(self, i: int, t: float) -> list[bytes]:
        c, n, now = self.codec, self.name, time.time_ns()
        yaw = 0.3 * t
        x, y = 2 * math.cos(yaw), 2 * math.sin(yaw)
        reg = c.registry
        out = [
            c.encode(
                make(reg, "sensor_msgs/msg/LaserScan", scan_values(360, 2.0 + 0.5 * math.sin(t))),
                "sensor_msgs/msg/LaserScan",
                f"/{n}/scan",
                publish_time_ns=now,
                seq=i,
            ),
            c.encode(
                make(
                    reg,
                    "nav_msgs/msg/Odometry",
                    {
                        "header": header("odom"),
                        "pose": {"pose": pose_values(x, y, yaw + math.pi / 2)},
                        "twist": {"twist": {"linear": {"x": 0.6}, "angular": {"z": 0.3}}},
                    },
                ),
                "nav_msgs/msg/Odometry",
                f"/{n}/odom",
                publish_time_ns=now,
                seq=i,
            ),
        ]
        if i % 5 == 0:
            out.append(
                encode_status(
                    n,
                    status="patrolling",
                    is_ok=True,
                    battery_level=0.8 - 0.001 * i,
                    location="lab",
                    publish_time_ns=now,
                    seq=i // 5 + 1,
                    codec=c,
                )
            )
            out.append(
                c.encode(
                    make(
                        reg,
                        "sensor_msgs/msg/CompressedImage",
                        {
                            "header": header("cam"),
                            "format": "jpeg",
                            "data": np.frombuffer(jpeg_bytes(), np.uint8),
                        },
                    ),
                    "sensor_msgs/msg/CompressedImage",
                    f"/{n}/camera/image/compressed",
                    publish_time_ns=now,
                    seq=i // 5 + 1,
                )
            )
            out.append(
                c.encode(
                    make(reg, "sensor_msgs/msg/PointCloud2", cloud_values(5000)),
                    "sensor_msgs/msg/PointCloud2",
                    f"/{n}/points",
                    publish_time_ns=now,
                    seq=i // 5 + 1,
                )
            )
            out += self._map_frames(now, i // 5 + 1)
        return out

    def _map_frames(self, now: int, seq: int) -> list[bytes]:
        c, n = self.codec, self.name
        cells = np.zeros((40, 40), dtype=np.int8)
        cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = 100  # walls
        cells[15:25, 15:25] = -1  # unknown
        grid = make(
            c.registry,
            "nav_msgs/msg/OccupancyGrid",
            {
                "header": header("map"),
                "info": {
                    "resolution": 0.2,
                    "width": 40,
                    "height": 40,
                    "origin": pose_values(-4.0, -4.0, 0.0),
                },
                "data": cells.ravel(),
            },
        )
        marker = {
            "header": header("map"),
            "ns": "t",
            "id": 1,
            "type": 9,
            "action": 0,
            "pose": pose_values(0.0, 3.0, 0.0),
            "scale": {"z": 0.5},
            "color": {"r": 1.0, "a": 1.0},
            "text": "dock",
        }
        cube = {
            **marker,
            "id": 2,
            "type": 1,
            "pose": pose_values(-2.0, -2.0, 0.5),
            "scale": {"x": 0.8, "y": 0.8, "z": 0.8},
            "color": {"g": 1.0, "a": 1.0},
        }
        markers = make(
            c.registry, "visualization_msgs/msg/MarkerArray", {"markers": [marker, cube]}
        )
        fix = make(
            c.registry,
            "sensor_msgs/msg/NavSatFix",
            {
                "header": header("gps"),
                "latitude": 30.2862,
                "longitude": -97.7365,
                "altitude": 150.0,
            },
        )
        method = CompressionCodec.DEFLATE if n == "r1" else CompressionCodec.ZSTD
        plain = c.encode(grid, "nav_msgs/msg/OccupancyGrid", f"/{n}/map", publish_time_ns=now,
                         seq=seq)
        map_frame = compress(plain, codec=method, topic=f"/{n}/map", no_drop=False, frame_codec=c)
        assert map_frame is not plain, "the test map must compress"
        return [
            map_frame,
            c.encode(
                markers,
                "visualization_msgs/msg/MarkerArray",
                f"/{n}/markers",
                publish_time_ns=now,
                seq=seq,
            ),
            c.encode(
                fix, "sensor_msgs/msg/NavSatFix", f"/{n}/gps/fix", publish_time_ns=now, seq=seq
            ),
        ]

    async def _publish(self) -> None:
        assert self.ws is not None
        t0 = time.monotonic()
        for i in itertools.count(1):
            for frame in self._frames(i, time.monotonic() - t0):
                await self.ws.send(frame)
            await asyncio.sleep(PUBLISH_PERIOD_S)


@dataclass
class Fleet:
    server: RelayServer
    robots: list[WsRobot]
    codec: Codec

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.server.port}/"


@contextlib.asynccontextmanager
async def running_fleet(tmp: Path, names: tuple[str, ...] = ("r1", "r2")):  # type: ignore[no-untyped-def]
    """Relay + robots, torn down on exit."""
    ips = {n: f"127.0.0.{i + 2}" for i, n in enumerate(names)}
    auth = load_auth_map(write_auth_map(tmp / "auth.yaml", ips))
    config = ServerConfig(
        listen_host="127.0.0.1",
        listen_port=0,
        auth_map=tmp / "auth.yaml",
        database=tmp / "fleet.db",
    )
    codec = Codec(TypeRegistry.default())
    async with RelayServer(config, auth) as server:
        url = f"ws://127.0.0.1:{server.port}/"
        robots = [WsRobot(n, ip, url, codec) for n, ip in ips.items()]
        try:
            for r in robots:
                await r.start()
            yield Fleet(server, robots, codec)
        finally:
            for r in robots:
                await r.stop()
