"""Robots whose every frame the test decides: a real relay, robots that are real WebSocket
clients on their own loopback address (as in fleet.py), but nothing is published unless the
test sends it, so a test knows exactly what the page could have received (TF trees, a map
sent once, video with a seq gap)."""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import load_auth_map
from fleetctl.server.config import ServerConfig
from fleetctl.wire.codec import Codec
from fleetctl.wire.metadata import read_metadata
from fleetctl.wire.registry import TypeRegistry
from tests.webviz.fleet import RobotConnection, write_auth_map
from tests.webviz.msgs import make
from tests.webviz.samples import header, pose_values, scan_values
from tests.webviz.video import EncodedUnit

TF_TYPE = "tf2_msgs/msg/TFMessage"
VIDEO_TYPE = "foxglove_msgs/msg/CompressedVideo"
KEYFRAME_REQUEST_TYPE = "fleetctl_msgs/msg/KeyframeRequest"

Transform = tuple[str, str, tuple[float, float, float], float]
"""(parent, child, translation in m, yaw in rad)."""


@dataclass
class ScriptedRobot(RobotConnection):
    """A robot connection that sends only what the test gives it, and keeps what it gets."""

    seqs: dict[str, int] = field(default_factory=dict)

    async def start(self) -> ScriptedRobot:
        await self.connect()
        return self

    def encode(self, type_name: str, topic: str, values: dict[str, Any], **kw: Any) -> bytes:
        """A frame on ``/<name><topic>``, numbered per topic as a robot numbers them."""
        full = f"/{self.name}{topic}"
        seq = self.seqs[full] = self.seqs.get(full, 0) + 1
        msg = make(self.codec.registry, type_name, values)
        return self.codec.encode(msg, type_name, full, seq=kw.pop("seq", seq),
                                 publish_time_ns=time.time_ns(), **kw)

    async def send(self, frame: bytes) -> None:
        assert self.ws is not None
        await self.ws.send(frame)

    def repeat(self, frames: Callable[[], Sequence[bytes]], period_s: float = 0.1) -> None:
        """Send ``frames()`` every *period_s* (a robot's publishing rate) until stopped."""

        async def loop() -> None:
            while True:
                for f in frames():
                    await self.send(f)
                await asyncio.sleep(period_s)

        self.tasks.append(asyncio.create_task(loop()))

    async def next_frame(self, type_name: str, timeout_s: float) -> bytes:
        """The next received frame of *type_name* (others are discarded)."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"{self.name}: no {type_name} within {timeout_s} s")
            frame = await asyncio.wait_for(self.received.get(), left)
            if read_metadata(frame).type == type_name:
                return frame


def tf_values(transforms: Sequence[Transform]) -> dict[str, Any]:
    """A TFMessage with the given (parent, child, xyz, yaw) edges."""
    return {
        "transforms": [
            {
                "header": header(parent),
                "child_frame_id": child,
                "transform": {
                    "translation": dict(zip("xyz", xyz, strict=True)),
                    "rotation": {"z": math.sin(yaw / 2), "w": math.cos(yaw / 2)},
                },
            }
            for parent, child, xyz, yaw in transforms
        ]
    }


def matrix_of(transforms: Sequence[Transform]) -> np.ndarray:
    """The 4x4 product of the edges, first one outermost (T_first_parent_last_child)."""
    m = np.eye(4)
    for _, _, (x, y, z), yaw in transforms:
        t = np.eye(4)
        t[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        t[:3, 3] = (x, y, z)
        m = m @ t
    return m


def scan_in(frame: str, beams: int = 360, radius_m: float = 2.0) -> dict[str, Any]:
    """A LaserScan in *frame* (a ring of ~radius_m)."""
    return {**scan_values(beams, radius_m), "header": header(frame)}


def grid_values(frame: str = "map", size: int = 40, resolution_m: float = 0.2) -> dict[str, Any]:
    """An OccupancyGrid with walls around and an unknown square in the middle."""
    cells = np.zeros((size, size), dtype=np.int8)
    cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = 100
    cells[size // 3 : size // 2, size // 3 : size // 2] = -1
    half = size * resolution_m / 2
    return {
        "header": header(frame),
        "info": {"resolution": resolution_m, "width": size, "height": size,
                 "origin": pose_values(-half, -half, 0.0)},
        "data": cells.ravel(),
    }


def video_values(unit: EncodedUnit, fmt: str, frame: str = "camera") -> dict[str, Any]:
    now = time.time_ns()
    return {
        "timestamp": {"sec": now // 1_000_000_000, "nanosec": now % 1_000_000_000},
        "frame_id": frame,
        "data": np.frombuffer(unit.data, dtype=np.uint8),
        "format": fmt,
    }


@dataclass
class VideoFeed:
    """Sends an encoded stream on one topic in order (cycling at its end, which is a
    keyframe boundary), or with a frame left out on purpose."""

    robot: ScriptedRobot
    topic: str
    units: list[EncodedUnit]
    fmt: str
    pos: int = 0
    running: bool = False
    task: asyncio.Task[None] | None = None

    async def send_next(self, *, skip: bool = False) -> EncodedUnit:
        """Send the next unit; with *skip*, number it as if one frame had been lost."""
        unit = self.units[self.pos % len(self.units)]
        self.pos += 1
        full = f"/{self.robot.name}{self.topic}"
        if skip:
            self.robot.seqs[full] = self.robot.seqs.get(full, 0) + 1
        frame = self.robot.encode(VIDEO_TYPE, self.topic, video_values(unit, self.fmt))
        await self.robot.send(frame)
        return unit

    def peek(self) -> EncodedUnit:
        return self.units[self.pos % len(self.units)]

    def run(self, period_s: float = 1 / 30) -> None:
        """Send at *period_s* (a camera's frame rate) until :meth:`stop`."""
        self.running = True

        async def loop() -> None:
            while self.running:
                await self.send_next()
                await asyncio.sleep(period_s)

        self.task = asyncio.create_task(loop())
        self.robot.tasks.append(self.task)

    async def stop(self) -> None:
        """Stop after the unit being sent (not cancelled mid-send: `pos` stays exact)."""
        self.running = False
        if self.task is not None:
            await self.task


@dataclass
class Relay:
    server: RelayServer
    codec: Codec
    robots: dict[str, ScriptedRobot]

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.server.port}/"


@contextlib.asynccontextmanager
async def scripted_fleet(tmp: Path, names: tuple[str, ...] = ("r1",)) -> AsyncIterator[Relay]:
    """A relay and connected scripted robots (r1 on 127.0.0.2, ...), torn down on exit."""
    ips = {n: f"127.0.0.{i + 2}" for i, n in enumerate(names)}
    auth = load_auth_map(write_auth_map(tmp / "auth.yaml", ips))
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=tmp / "auth.yaml",
                          database=tmp / "fleet.db")
    codec = Codec(TypeRegistry.default())
    async with RelayServer(config, auth) as server:
        url = f"ws://127.0.0.1:{server.port}/"
        robots = {n: ScriptedRobot(n, ip, url, codec) for n, ip in ips.items()}
        try:
            for r in robots.values():
                await r.start()
            yield Relay(server, codec, robots)
        finally:
            for r in robots.values():
                await r.stop()
