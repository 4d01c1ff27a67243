"""Camera as video with real parts: a real rclpy camera, the real client, the real server,
and a WebSocket viewer that decodes the CompressedVideo frames.

- The robot ``cam1`` (source 127.0.1.5, ROS domain 61) runs ``fleetctl client`` with two
  video entries on the simulated camera's ``/camera/image_raw`` (15 Hz, rgb8 320x240 with
  motion, texture and noise: :mod:`fleetctl.client.ros.simcamera`): ``/cam1/camera``
  (a keyframe every second) and ``/cam1/camera_slow`` (every 600 s, so that only a
  request makes one).
- A KeyframeRequest delivered to a real :class:`Bridge` (domain 62) makes its next frame a
  keyframe (the client's side of the request, without a server).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")

from fleetctl.demo.fleet import free_port
from fleetctl.demo.run import http_ok, online_robots
from fleetctl.waiting import wait_until
from tests.client.ros.harness import JsonProc, fleetctl_argv, spun_bridge, write_yaml

pytestmark = [pytest.mark.ros, pytest.mark.slow]
DOMAIN_ID = 62  # the in-process bridge test (this file's range: 61-62)
ROBOT_DOMAIN = 61
OPERATOR_TOKEN = "operator-token-for-video-tests"
STARTUP_S = 30.0
REPO = Path(__file__).resolve().parents[3]
VIDEO_TYPE = "foxglove_msgs/msg/CompressedVideo"
CAMERA_SIZE = "320x240"


@dataclass
class Fleet:
    root: Path
    port: int
    server: JsonProc
    client: JsonProc
    camera: JsonProc

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/"


def _configs(root: Path, port: int) -> None:
    write_yaml(root / "server.yaml", {"listen_host": "127.0.0.1", "listen_port": port,
                                      "auth_map": "auth.yaml", "database": "fleet.db"})
    write_yaml(root / "auth.yaml", {"version": 1, "identities": [
        {"name": "cam1", "ip": "127.0.1.5", "rules": [
            {"topic": "/cam1/.*", "op": "send"},
            {"topic": "/keyframe_requests", "op": "receive"}]},
        {"name": "operator",
         "token_sha256": hashlib.sha256(OPERATOR_TOKEN.encode()).hexdigest(),
         "rules": [{"topic": ".*", "op": "receive"},
                   {"topic": "/keyframe_requests", "op": "send"}]},
    ]})
    camera = {"topic": "/camera/image_raw", "type": "sensor_msgs/msg/Image", "priority": 2}
    write_yaml(root / "cam1.yaml", {
        "server_url": f"ws://127.0.0.1:{port}/", "robot_name": "cam1",
        "bind_address": "127.0.1.5",
        "publish": [
            {**camera, "remote_topic": "/cam1/camera",
             "video": {"codec": "h264", "keyframe_interval_s": 1.0}},
            {**camera, "remote_topic": "/cam1/camera_slow",
             "video": {"codec": "vp8", "keyframe_interval_s": 600.0}},
        ],
        "limits": {"reconnect_min_s": 0.1, "reconnect_max_s": 0.5}})


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    root = tmp_path_factory.mktemp("video")
    port = free_port()
    _configs(root, port)
    env = {"ROS_DOMAIN_ID": str(ROBOT_DOMAIN)}
    server = JsonProc(fleetctl_argv("server", "--config", str(root / "server.yaml")), {},
                      root / "server.log")
    procs = [server]
    try:
        wait_until(lambda: http_ok(f"http://127.0.0.1:{port}/healthz"), STARTUP_S,
                   describe="server")
        client = JsonProc(fleetctl_argv("client", "--config", str(root / "cam1.yaml"),
                                        "--print-stats"), env, root / "client.log")
        procs.append(client)
        # 320x240 (230 KB a frame), not a driver's 640x480: what is tested is the path
        # (encode, relay, decode, keyframe requests), and two CI machines ran it at 0.1-0.3
        # frames/s with 921 KB frames (two encoders and DDS on two loaded cores).
        camera = JsonProc([sys.executable, "-m", "fleetctl.client.ros.simcamera",
                           "/camera/image_raw", "15", CAMERA_SIZE], env, root / "camera.log")
        procs.append(camera)
        wait_until(lambda: "cam1" in online_robots(f"http://127.0.0.1:{port}"), STARTUP_S,
                   describe="cam1 online")
        # Online comes with the robot's first frame of any topic. A viewer subscribing
        # before the server saw a video topic's first frame gets no automatic keyframe
        # request, and camera_slow makes keyframes only on request: wait for both topics.
        wait_until(lambda: _video_topics_seen(port), STARTUP_S,
                   describe="both video topics at the server")
        yield Fleet(root, port, server, client, camera)
    finally:
        codes = {proc: proc.stop() for proc in reversed(procs)}
    client = procs[1]
    assert codes[client] == 0, client.stderr_tail()  # SIGTERM: a clean shutdown
    stats = [*client.received, *client.lines.queue][-1]  # a timeout's report may have taken it
    video = stats["video"]["/cam1/camera"]
    assert video["frames_sent"] > 0 and video["errors"] == 0


def _video_topics_seen(port: int) -> bool:
    """Whether the server counted frames in on both video topics (``/metrics``)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as resp:
        text = resp.read().decode()
    return all(f'fleetctl_messages_in_total{{topic="{t}"}}' in text
               for t in ("/cam1/camera", "/cam1/camera_slow"))


def _auto_keyframe_requests(port: int) -> float:
    """Keyframe requests the server made by itself for new subscribers (``/metrics``)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as resp:
        for line in resp.read().decode().splitlines():
            if line.startswith('fleetctl_keyframe_requests_total{outcome="auto"}'):
                return float(line.split()[-1])
    return 0.0


class Viewer:
    """An operator's WebSocket that decodes one video topic with the test decoder."""

    def __init__(self, ws: Any, topic: str, codec: str) -> None:
        from fleetctl.client.video import VideoDecoder
        from fleetctl.wire.codec import Codec
        from fleetctl.wire.registry import TypeRegistry

        self.ws = ws
        self.topic = topic
        self.codec = Codec(TypeRegistry.default())
        self.decoder = VideoDecoder(codec)
        self.shown: list[tuple[int, bool, Any]] = []  # (seq, keyframe, picture)
        self.received: list[tuple[float, int, bool]] = []  # (time, seq, keyframe)
        self.skip_seqs: set[int] = set()
        # Until the first picture, ask for a keyframe (at most once a second) when a frame
        # cannot be decoded, as the page does: the keyframe the server asked for when this
        # viewer subscribed can be lost on the way (its fragments replaced by a newer frame
        # in a latest-only queue of a loaded machine), and this topic makes no other.
        self.asked_while_starting = 0
        self._asked_s = -1.0

    async def run(self) -> None:
        from fleetctl.client.videobits import is_keyframe
        from fleetctl.wire.whole_messages import whole_messages

        async for message in whole_messages(self.ws):
            meta, msg = self.codec.decode(message)
            if meta.topic != self.topic or meta.type != VIDEO_TYPE:
                continue
            data = bytes(msg.data)
            keyframe = is_keyframe(msg.format, data)
            self.received.append((time.monotonic(), meta.seq, keyframe))
            if meta.seq in self.skip_seqs:
                continue  # as if lost on the way
            picture = self.decoder.decode(data, meta.seq)
            if picture is not None:
                self.shown.append((meta.seq, keyframe, picture))
            elif not self.shown and time.monotonic() - self._asked_s >= 1.0:
                self._asked_s = time.monotonic()
                self.asked_while_starting += 1
                await self.request_keyframe()

    async def request_keyframe(self) -> None:
        from fleetctl.client.video import KEYFRAME_REQUEST_TOPIC, KEYFRAME_REQUEST_TYPE

        request = self.codec.registry.typestore.types[KEYFRAME_REQUEST_TYPE](topic=self.topic)
        await self.ws.send(self.codec.encode(request, KEYFRAME_REQUEST_TYPE,
                                             KEYFRAME_REQUEST_TOPIC))


@contextlib.asynccontextmanager
async def viewer(url: str, topic: str, codec: str) -> AsyncIterator[Viewer]:
    from websockets.asyncio.client import connect

    from fleetctl.wire.control import encode_subscription

    async with connect(url, additional_headers={"Authorization": f"Bearer {OPERATOR_TOKEN}"},
                       max_size=None, ping_interval=None) as ws:
        await ws.send(encode_subscription(topic))
        view = Viewer(ws, topic, codec)
        task = asyncio.create_task(view.run())
        try:
            yield view
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


async def until(predicate: Any, timeout_s: float, what: str,
                seen: Any = lambda: "") -> None:
    """Poll *predicate* until true; fail after *timeout_s* with *what* and ``seen()``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}; {seen()}"
        await asyncio.sleep(0.02)


def _where_frames_went(fleet: Fleet, view: Viewer) -> str:
    """What each stage saw, for a timeout: the viewer's frames, the relay's count of the
    camera's video frames (``/metrics``), the client's last log lines."""
    keys = sum(key for _, _, key in view.received)
    with urllib.request.urlopen(f"http://127.0.0.1:{fleet.port}/metrics", timeout=5) as resp:
        counts = [line for line in resp.read().decode().splitlines()
                  if line.startswith("fleetctl_messages_in_total") and "/cam1/" in line]
    return (f"viewer received {len(view.received)} frames ({keys} keyframes), decoded "
            f"{len(view.shown)}, asked for {view.asked_while_starting} keyframes; the relay "
            f"counted {counts}; {_client_video_stats(fleet)}; load {os.getloadavg()}, "
            f"busiest processes:\n{_busiest_processes()}\nclient log:\n"
            f"{fleet.client.stderr_tail()}")


def _client_video_stats(fleet: Fleet) -> str:
    """The client's counts of camera frames in, replaced, skipped and sent. It prints its
    stats only when it stops: this stops it (the next test of the module then fails too)."""
    fleet.client.signal(signal.SIGTERM)
    try:
        stats = fleet.client.wait_for(lambda line: "video" in line, 15.0, "the client's stats")
    except AssertionError as exc:
        return f"no client stats ({exc})"
    return (f"the client (stopped to print them) counted video {stats['video']} and local "
            f"camera messages in {stats['bridge'].get('local_in')}")


def _busiest_processes() -> str:
    """``ps``'s ten busiest processes: whether something beside the test took the CPU."""
    out = subprocess.run(["ps", "-eo", "pcpu,rss,etimes,args", "--sort=-pcpu"],
                         capture_output=True, text=True, check=False).stdout
    return "\n".join(line[:160] for line in out.splitlines()[:11])


def test_viewer_decodes_the_cameras_video(fleet: Fleet) -> None:
    async def scenario() -> Viewer:
        async with viewer(fleet.url, "/cam1/camera", "h264") as view:
            # ~2 s on an idle machine; a loaded one (CI, every test before this one) has
            # taken far longer.
            await until(lambda: len(view.shown) >= 20, 2 * STARTUP_S, "20 decoded frames",
                        lambda: _where_frames_went(fleet, view))
            return view

    view = asyncio.run(scenario())
    seqs = [seq for seq, _, _ in view.shown]
    _, first_key, picture = view.shown[0]
    assert first_key, "a late viewer starts at a keyframe"
    assert picture.shape == (240, 320, 3) and 20 < float(picture.mean()) < 235
    # Nothing shown after a gap unless from a keyframe.
    for (prev, _, _), (seq, key, _) in zip(view.shown, view.shown[1:], strict=False):
        assert seq == prev + 1 or key, (prev, seq)
    assert seqs == sorted(seqs)
    # Keyframes once a second at 15 Hz (~1 in 15), plus one per frame the link dropped
    # and one per encoder reopen, which a loaded machine makes more frequent: the bound
    # only says the stream is mostly delta frames, which the viewer decoded too.
    keys = sum(key for _, _, key in view.received)
    assert 1 <= keys <= len(view.received) // 2, (keys, len(view.received))
    assert any(not key for _, key, _ in view.shown), "delta frames decoded"


def _server_routes_keyframe_requests() -> bool:
    sources = (REPO / "fleetctl" / "server").glob("*.py")
    return any("KeyframeRequest" in path.read_text(encoding="utf-8") for path in sources)


# How long the robot may take to answer a keyframe request (seconds).
ANSWER_S = 15.0


def test_viewer_keyframe_request_reaches_the_robot_through_the_server(fleet: Fleet) -> None:
    if not _server_routes_keyframe_requests():
        pytest.skip("the server does not route /keyframe_requests yet (helper LATCH's part)")

    async def scenario() -> tuple[Viewer, float, float]:
        async with viewer(fleet.url, "/cam1/camera_slow", "vp8") as view:
            # The server asks the robot for a keyframe when this viewer subscribes (and the
            # viewer asks again while it cannot decode, as the page does).
            await until(lambda: len(view.shown) >= 5, STARTUP_S, "frames after subscribing")
            assert _auto_keyframe_requests(fleet.port) >= 1
            # Lose the next frame: the decoder stops until a keyframe, and asks for one.
            view.skip_seqs.add(view.received[-1][1] + 1)
            await until(lambda: view.decoder.stats.gaps >= 1, 5.0, "the gap")
            asked = time.monotonic()
            await view.request_keyframe()
            shown = len(view.shown)
            await until(lambda: len(view.shown) > shown, ANSWER_S, "a keyframe after the request")
            return view, asked, view.received[-1][0]

    view, asked, _ = asyncio.run(scenario())
    after = [(t, key) for t, _, key in view.received if t >= asked]
    first_key_s = next(t for t, key in after if key)
    # Periodic keyframes on this topic come every 600 s: one within ANSWER_S answers the
    # request. Not 2 s: a CI machine busy encoding a 15 Hz 921 KB camera took 2.85 s.
    assert first_key_s - asked < ANSWER_S


# -- the client side of a request, with a real Bridge and no server ---------------------


@pytest.fixture
def bridge_and_camera(ros: tuple[Any, Any]) -> Iterator[tuple[Any, Any, list[Any]]]:
    from fleetctl.client.ros.simcamera import CAMERA_QOS, SimCamera

    context, peer = ros
    sent: list[tuple[bytes, bool]] = []
    lock = threading.Lock()

    def send_video(spec: Any, frame: bytes, keyframe: bool) -> None:
        with lock:
            sent.append((frame, keyframe))

    camera_entry = {"topic": "/camera/image_raw", "type": "sensor_msgs/msg/Image",
                    "video": {"codec": "h264", "keyframe_interval_s": 600.0}}
    with spun_bridge(context, camera_entry, send_video) as bridge:
        assert CAMERA_QOS.depth == 1
        camera = SimCamera(peer, "/camera/image_raw", 15.0, 320, 240)
        yield bridge, camera, sent


def test_keyframe_request_frame_makes_the_next_frame_a_keyframe(
        bridge_and_camera: tuple[Any, Any, list[tuple[bytes, bool]]]) -> None:
    from fleetctl.client.video import KEYFRAME_REQUEST_TOPIC, KEYFRAME_REQUEST_TYPE
    from fleetctl.wire.codec import Codec
    from fleetctl.wire.registry import TypeRegistry

    bridge, _camera, sent = bridge_and_camera
    # Past the encoder's frame-rate check (8 frames): it was opened for 30 Hz, the camera
    # runs at 15, so it reopens once (one more keyframe) before it settles.
    wait_until(lambda: len(sent) >= 12, STARTUP_S, describe="twelve video frames")
    keys = [key for _, key in sent[:12]]
    assert keys[0] and sum(keys) <= 2, keys
    codec = Codec(TypeRegistry.default())
    types = codec.registry.typestore.types

    def request(topic: str) -> bytes:
        return codec.encode(types[KEYFRAME_REQUEST_TYPE](topic=topic), KEYFRAME_REQUEST_TYPE,
                            KEYFRAME_REQUEST_TOPIC)

    bridge.deliver(request("/r1/other"))  # not ours: counted, nothing changes
    assert bridge.stats.unmatched == 1
    before = len(sent)
    bridge.deliver(request("/r1/camera/image_raw"))
    wait_until(lambda: len(sent) > before + 5, 10.0, describe="frames after the request")
    # The next frame, or the one after if the worker was encoding when the request came.
    keys = [key for _, key in sent[before:before + 6]]
    assert keys[0] or keys[1], keys
    first = 0 if keys[0] else 1
    assert not any(keys[first + 1:first + 5]), keys  # one keyframe, not a run of them
    assert bridge.videos["/r1/camera/image_raw"].stats.keyframe_requests == 1
    meta, msg = codec.decode(sent[before + first][0])
    assert meta.type == "foxglove_msgs/msg/CompressedVideo" and msg.frame_id == "camera"
    assert json.dumps(vars(bridge.videos["/r1/camera/image_raw"].stats))  # JSON-able
