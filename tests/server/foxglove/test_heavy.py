"""A Foxglove viewer of heavy topics (a Nav2 Path of 2,000 poses) through a real relay:
the conversion to CDR runs off the event loop, and a converter slower than the frames
come gives the viewer the newest, in order, the superseded ones counted and said once."""

from __future__ import annotations

import logging
import time
from collections.abc import AsyncIterator
from typing import Any

import pytest

from fleetctl.server.app import RelayServer
from fleetctl.server.foxglove.transcode import SharedTranscoder
from fleetctl.wire.codec import default_codec
from tests.server.conftest import ALICE_TOKEN, client, wait_for
from tests.server.foxglove.conftest import REFERENCE
from tests.server.foxglove.fxclient import Viewer, https_get, open_viewer, ticket

PATH_TYPE = "nav_msgs/msg/Path"
TOPIC = "/husky1/plan"
CODEC = default_codec()


def path_frame(seq: int, poses: int = 2000) -> bytes:
    """A planner's Path (the robot graph's, docs/benchmarks.md), its header stamped *seq*
    seconds: which frame a viewer got."""
    t = CODEC.registry.typestore.types

    def header() -> Any:
        return t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=seq, nanosec=0), frame_id="map")

    quat = t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    msg = t[PATH_TYPE](header=header(), poses=[
        t["geometry_msgs/msg/PoseStamped"](header=header(), pose=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=0.05 * k, y=0.0, z=0.0),
            orientation=quat)) for k in range(poses)])
    return CODEC.encode(msg, PATH_TYPE, TOPIC, seq=seq, publish_time_ns=time.time_ns())


@pytest.fixture(scope="module")
def paths() -> list[bytes]:
    return [path_frame(seq) for seq in range(8)]


@pytest.fixture
async def subscribed(fx_server: RelayServer, paths: list[bytes]) -> AsyncIterator[
        tuple[Any, Viewer]]:
    """husky1 (a robot) sending the Path, alice's Foxglove viewer subscribed to it."""
    async with client(fx_server, source="127.0.0.2") as robot:
        await robot.send(paths[0])  # the catalog learns the channel
        await wait_for(lambda: bool(fx_server.foxglove.catalog.channels()))
        port = fx_server.web_port
        async with open_viewer(port, await ticket(port, ALICE_TOKEN)) as ws:
            viewer = Viewer(ws)
            await viewer.until(lambda: viewer.channel(TOPIC) is not None)
            channel = viewer.channel(TOPIC)
            assert channel is not None
            await viewer.subscribe(1, channel["id"])
            await wait_for(lambda: bool(fx_server.core.subs.receivers(TOPIC)))
            yield robot, viewer


def stamps(viewer: Viewer) -> list[int]:
    return [REFERENCE.deserialize_cdr(payload, PATH_TYPE).header.stamp.sec
            for _, _, payload in viewer.messages]


async def test_conversion_does_not_run_on_the_loops_thread(
        fx_server: RelayServer, paths: list[bytes], subscribed: tuple[Any, Viewer]) -> None:
    # What converting these frames costs a thread, measured here on a cache of our own.
    own = SharedTranscoder(CODEC, 1 << 26)
    costs = []
    for frame in paths:
        start = time.thread_time()
        assert own.convert(bytes(frame)) is not None
        costs.append(time.thread_time() - start)
    robot, viewer = subscribed
    transcoded = fx_server.foxglove.transcoder.transcoded
    # This test's loop is the relay's: the CPU its thread spends while the relay converts
    # every frame (one at a time, each awaited: none superseded) is the loop's share.
    start = time.thread_time()
    for n, frame in enumerate(paths, 1):
        await robot.send(frame)
        await viewer.until(lambda n=n: len(viewer.messages) >= n, timeout_s=30)
    loop_cpu = time.thread_time() - start
    assert fx_server.foxglove.transcoder.transcoded - transcoded == len(paths)
    assert stamps(viewer) == list(range(len(paths)))
    # On the loop (before), its thread spent at least the conversions' sum; off the loop
    # it spends what reading, routing and writing cost, a small part of it.
    assert loop_cpu < sum(costs) / 3, (loop_cpu, costs)


async def test_a_slower_converter_gives_the_newest_frame_counted_and_said_once(
        fx_server: RelayServer, paths: list[bytes], subscribed: tuple[Any, Viewer],
        caplog: pytest.LogCaptureFixture) -> None:
    robot, viewer = subscribed
    caplog.set_level(logging.WARNING, logger="fleetctl.server.foxglove")
    (peer,) = fx_server.core.subs.receivers(TOPIC)
    outbound = peer.outbound
    # A burst: the frames after the first arrive while the first converts (a Path takes
    # ~13x longer to convert than to read), so they supersede each other in the viewer's
    # latest-per-topic slot; twice, to see the log line said once.
    last = len(paths) - 1
    for burst in range(2):
        before = len(viewer.messages)
        for frame in paths:
            await robot.send(frame)
        await viewer.until(lambda b=before: last in stamps(viewer)[b:], timeout_s=30)
        got = stamps(viewer)[before:]
        assert got == sorted(set(got)) and got[-1] == last and len(got) < len(paths), got
        assert len(viewer.messages) + outbound.drops.get(TOPIC, 0) == len(paths) * (burst + 1)
    superseded = fx_server.foxglove.superseded
    assert 1 <= superseded <= outbound.drops[TOPIC]
    status, body = await https_get(fx_server.port, "/metrics", secure=False)
    assert status == 200
    assert f"fleetctl_foxglove_superseded_total {superseded}" in body.decode()
    said = [r.getMessage() for r in caplog.records if "superseded" in r.getMessage()]
    assert len(said) == 1 and TOPIC in said[0], said  # once per topic, two bursts
