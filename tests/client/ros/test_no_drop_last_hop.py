"""Integration: a burst of no_drop frames through a real relay reaches a slow local
subscriber of the receiving robot complete and in order (the last hop).

A real server process, a real ``fleetctl client`` (robot ``bravo``, ROS domain of this
file) subscribing ``/ops/events`` onto local ``/ops_events``, an operator connection that
sends 200 no_drop events of 10 KB at once, and two real rclpy listener processes on the
robot (RELIABLE, depth 1000): one spun normally, one paused (SIGSTOP) while the whole
burst is republished, as a loaded robot's node is descheduled. Before the client's
republishing writers were deep (fleetctl.client.ros.republish), its KEEP_LAST 10 writer
overwrote what the paused listener had not taken: it got 51 of the 200 (Fast DDS's 0.5 MB
shared-memory segment held the rest until they were overwritten).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")

from rclpy.serialization import deserialize_message

from fleetctl.demo.fleet import free_port
from fleetctl.demo.run import http_ok, online_robots
from fleetctl.waiting import wait_until
from tests.client.ros.harness import JsonProc, fleetctl_argv, ros_helper, write_yaml
from tests.support import ros_domain_alone

pytestmark = [pytest.mark.ros, pytest.mark.slow]
DOMAIN_ID = ros_domain_alone(29)  # free in the client tests' 20-39; spares 91-99
OPERATOR_TOKEN = "operator-token-for-last-hop"
ROBOT_IP = "127.0.1.9"
STARTUP_S = 30.0
COUNT = 200
PAD = "x" * 10_000  # an event with a payload: 200 of them exceed a 0.5 MB SHM segment
WARMUP = "warmup"
TYPE = "std_msgs/msg/String"


def _configs(root: Path, port: int) -> None:
    write_yaml(root / "server.yaml", {"listen_host": "127.0.0.1", "listen_port": port,
                                      "auth_map": "auth.yaml", "database": "fleet.db"})
    write_yaml(root / "auth.yaml", {"version": 1, "identities": [
        {"name": "bravo", "ip": ROBOT_IP, "rules": [
            {"topic": "/bravo/.*", "op": "send"}, {"topic": "/ops/events", "op": "receive"}]},
        {"name": "operator",
         "token_sha256": hashlib.sha256(OPERATOR_TOKEN.encode()).hexdigest(),
         "rules": [{"topic": ".*", "op": "receive"}, {"topic": "/ops/events", "op": "send"}]},
    ]})
    write_yaml(root / "bravo.yaml", {
        "server_url": f"ws://127.0.0.1:{port}/", "robot_name": "bravo",
        "bind_address": ROBOT_IP,
        "subscribe": [{"remote_topic": "/ops/events", "type": TYPE,
                       "local_topic": "/ops_events"}],
        "limits": {"reconnect_min_s": 0.1, "reconnect_max_s": 0.5}})


@pytest.fixture
def fleet(tmp_path: Path) -> Iterator[tuple[Path, int]]:
    """``(root, port)`` of a running server with robot bravo's client online."""
    port = free_port()
    _configs(tmp_path, port)
    server = JsonProc(fleetctl_argv("server", "--config", str(tmp_path / "server.yaml")), {},
                      tmp_path / "server.log")
    client = None
    try:
        wait_until(lambda: http_ok(f"http://127.0.0.1:{port}/healthz"), STARTUP_S,
                   describe="server")
        client = JsonProc(fleetctl_argv("client", "--config", str(tmp_path / "bravo.yaml")),
                          {"ROS_DOMAIN_ID": str(DOMAIN_ID)}, tmp_path / "bravo.log")
        wait_until(lambda: "bravo" in online_robots(f"http://127.0.0.1:{port}"), STARTUP_S,
                   describe="bravo online")
        yield tmp_path, port
    finally:
        if client is not None:
            client.stop()
        server.stop()


def _frames() -> tuple[bytes, list[bytes]]:
    """A droppable warm-up frame and COUNT no_drop events, as an operator sends them."""
    from fleetctl.wire.codec import Codec
    from fleetctl.wire.registry import TypeRegistry

    codec = Codec(TypeRegistry.default())
    string = codec.registry.typestore.types[TYPE]
    now = time.time_ns()
    warmup = codec.encode(string(data=WARMUP), TYPE, "/ops/events", publish_time_ns=now)
    events = [codec.encode(string(data=f"event-{i}-{PAD}"), TYPE, "/ops/events",
                           no_drop=True, seq=i, publish_time_ns=now + i)
              for i in range(1, COUNT + 1)]
    return warmup, events


def _collector(got: list[str], until: str) -> Callable[[dict[str, Any]], bool]:
    """A listener predicate keeping each event's name in *got*; true at *until*."""
    from std_msgs.msg import String

    def take(line: dict[str, Any]) -> bool:
        if "cdr" not in line:
            return False
        text = deserialize_message(bytes.fromhex(line["cdr"]), String).data
        if text != WARMUP:
            got.append("-".join(text.split("-")[:2]))  # event-N, without the payload
        return bool(got) and got[-1] == until

    return take


async def _operator(port: int, warmed: asyncio.Future[None], burst: asyncio.Event,
                    done: asyncio.Event) -> None:
    """Send warm-ups until *warmed*, then the COUNT events at once when *burst* is set;
    close when *done* is set."""
    from websockets.asyncio.client import connect

    warmup, events = _frames()
    async with connect(f"ws://127.0.0.1:{port}/", ping_interval=None, max_size=None,
                       additional_headers={"Authorization": f"Bearer {OPERATOR_TOKEN}"}) as ws:
        assert json.loads(await asyncio.wait_for(ws.recv(), 10))["type"] == "welcome"
        while not warmed.done():  # every DDS hop matched once one warm-up got through
            await ws.send(warmup)
            await asyncio.wait([warmed], timeout=0.2)
        await burst.wait()
        for frame in events:
            await ws.send(frame)
        await done.wait()


def test_a_no_drop_burst_reaches_a_paused_local_subscriber_complete(
        fleet: tuple[Path, int]) -> None:
    root, port = fleet
    slow = ros_helper("listen", ["/ops_events", TYPE], DOMAIN_ID, root / "slow.log")
    fast = ros_helper("listen", ["/ops_events", TYPE], DOMAIN_ID, root / "fast.log")
    try:
        for listener in (slow, fast):
            listener.wait_for(lambda line: line.get("ready", False), STARTUP_S, "a listener")
        expected = [f"event-{i}" for i in range(1, COUNT + 1)]
        slow_got: list[str] = []
        fast_got: list[str] = []

        async def scenario() -> None:
            loop = asyncio.get_running_loop()
            warmed: asyncio.Future[None] = loop.create_future()
            burst, done = asyncio.Event(), asyncio.Event()
            operator = asyncio.create_task(_operator(port, warmed, burst, done))
            for listener in (slow, fast):
                await loop.run_in_executor(None, lambda p=listener: p.wait_for(
                    lambda line: "cdr" in line, STARTUP_S, "a warm-up"))
            warmed.set_result(None)
            slow.signal(signal.SIGSTOP)
            try:
                burst.set()
                # Every event published on the robot: the spun listener has them all.
                await loop.run_in_executor(None, lambda: fast.wait_for(
                    _collector(fast_got, f"event-{COUNT}"), STARTUP_S, "the burst"))
            finally:
                slow.signal(signal.SIGCONT)
                done.set()
            await operator

        asyncio.run(asyncio.wait_for(scenario(), 3 * STARTUP_S))
        assert fast_got == expected
        # DDS repairs on the writer's heartbeat (~3 s): what is still in its history
        # arrives within a few of them; what was overwritten never does.
        take = _collector(slow_got, f"event-{COUNT}")
        with contextlib.suppress(AssertionError):  # compared below, with what did arrive
            slow.wait_for(take, 15.0, f"event-{COUNT} on the paused listener")
        assert len(slow_got) == COUNT, f"{COUNT - len(slow_got)} lost: {slow_got[:5]} ..."
        assert slow_got == expected
    finally:
        slow.stop()
        fast.stop()


def _bridge(context: Any) -> Any:
    """A real client node of robot r1 receiving ``/ops/events`` (onto ``/ops_events``) and
    ``/cams/.*`` (under their own names), whose link drops what it is handed."""
    from fleetctl.client.config import parse_client_config
    from fleetctl.client.ros.bridge import Bridge, LinkPort
    from fleetctl.client.ros.runner import status_encoder
    from fleetctl.wire.codec import Codec
    from fleetctl.wire.registry import TypeRegistry

    codec = Codec(TypeRegistry.default())
    config = parse_client_config({
        "server_url": "ws://127.0.0.1:1/", "robot_name": "r1",
        "subscribe": [{"remote_topic": "/ops/events", "type": TYPE,
                       "local_topic": "/ops_events"},
                      {"remote_topic": "/cams/.*", "type": TYPE}]}, source="test.yaml")
    port = LinkPort(admit=lambda topic: True, send=lambda spec, frame, ns: None,
                    send_status=lambda frame: None)
    return Bridge(config, codec, codec.registry.typestore, port, status_encoder(codec, "r1"),
                  context=context)


def _depths(bridge: Any, topic: str) -> list[int]:
    """History depths of the bridge's rclpy publishers of local *topic* (the ROS graph
    reports 0 for any writer: DDS does not tell others a writer's depth)."""
    return [publisher.qos_profile.depth for publisher in bridge.publishers
            if publisher.topic_name == topic]


def test_republishing_writers_are_deep_and_a_burst_beyond_them_is_said_once(
        ros: tuple[Any, Any], caplog: pytest.LogCaptureFixture) -> None:
    from fleetctl.client.ros.republish import DEEP_DEPTH
    from fleetctl.wire.codec import Codec
    from fleetctl.wire.registry import TypeRegistry

    context, _peer = ros
    codec = Codec(TypeRegistry.default())
    string = codec.registry.typestore.types[TYPE]
    bridge = _bridge(context)
    try:
        # Deep from its creation: the first burst finds it matched and deep.
        assert _depths(bridge, "/ops_events") == [DEEP_DEPTH]
        for i in range(1, DEEP_DEPTH + 6):
            bridge.deliver(codec.encode(string(data=f"event-{i}"), TYPE, "/ops/events",
                                        no_drop=True, seq=i, publish_time_ns=i))
        assert bridge.stats.published_local == DEEP_DEPTH + 5
        # The 5 past the depth, all within the ack window: at risk, counted, said once.
        assert bridge.stats.no_drop_at_risk == 5
        assert bridge.stats.per_topic_at_risk == {"/ops/events": 5}
        said = [r for r in caplog.records if "no_drop_at_risk" in r.getMessage()]
        assert len(said) == 1 and "/ops/events" in said[0].getMessage()
    finally:
        bridge.destroy_node()


def test_a_big_droppable_stream_gets_a_shallow_writer(ros: tuple[Any, Any]) -> None:
    from fleetctl.client.ros.republish import BIG_DROPPABLE_BYTES, DEEP_DEPTH, SHALLOW_DEPTH
    from fleetctl.wire.codec import Codec
    from fleetctl.wire.registry import TypeRegistry

    context, _peer = ros
    codec = Codec(TypeRegistry.default())
    string = codec.registry.typestore.types[TYPE]
    bridge = _bridge(context)
    try:
        small = codec.encode(string(data="x"), TYPE, "/cams/a")
        big = codec.encode(string(data="x" * BIG_DROPPABLE_BYTES), TYPE, "/cams/b")
        bridge.deliver(small)
        bridge.deliver(big)
        assert _depths(bridge, "/cams/a") == [DEEP_DEPTH]
        assert _depths(bridge, "/cams/b") == [SHALLOW_DEPTH]
        bridge.deliver(small)  # a small one later: the big stream's writer stays shallow
        bridge.deliver(codec.encode(string(data="y"), TYPE, "/cams/b"))
        assert _depths(bridge, "/cams/b") == [SHALLOW_DEPTH]
        assert bridge.stats.published_local == 4
    finally:
        bridge.destroy_node()
