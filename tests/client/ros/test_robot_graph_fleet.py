"""``/rosout`` through a real client and a real relay: a stream, not a latched topic.

rcl publishes every node's log on ``/rosout`` TRANSIENT_LOCAL (depth 1000, lifespan 10 s),
so on a robot every ``/rosout`` publisher offers it, and the client subscribed
transient-local and sent each log line marked latched: the relay kept the last one as the
state of ``/rosout`` for every later viewer, as it does a map. Here a node of this test
publishes log lines with rcl's rosout QoS (as rclcpp's logger does) beside the real
``fleetctl client`` (robot ``alpha``, domain 85); a viewer of the real relay checks the
frames it gets once the client has matched its publishers' QoS.
"""

from __future__ import annotations

import asyncio
import hashlib
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")

from fleetctl.demo.fleet import free_port  # noqa: E402
from fleetctl.demo.run import http_ok, online_robots  # noqa: E402
from fleetctl.waiting import wait_until  # noqa: E402
from fleetctl.wire.metadata import read_metadata  # noqa: E402
from tests.client.ros.harness import JsonProc, fleetctl_argv, write_yaml  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]
DOMAIN_ID = 85  # this file's own ROS domain
ALPHA_IP = "127.0.1.85"
TOKEN = "viewer-token-for-rosout-tests"
STARTUP_S = 30.0


@pytest.fixture
def fleet(tmp_path: Path) -> Iterator[tuple[int, JsonProc]]:
    """A relay and robot alpha's client sending ``/rosout``: (relay port, client)."""
    port = free_port()
    write_yaml(tmp_path / "server.yaml", {"listen_host": "127.0.0.1", "listen_port": port,
                                          "auth_map": "auth.yaml", "database": "fleet.db"})
    write_yaml(tmp_path / "auth.yaml", {"version": 1, "identities": [
        {"name": "alpha", "ip": ALPHA_IP, "rules": [{"topic": "/alpha/.*", "op": "send"}]},
        {"name": "viewer", "token_sha256": hashlib.sha256(TOKEN.encode()).hexdigest(),
         "rules": [{"topic": ".*", "op": "receive"}]}]})
    write_yaml(tmp_path / "alpha.yaml", {
        "server_url": f"ws://127.0.0.1:{port}/", "robot_name": "alpha",
        "bind_address": ALPHA_IP,
        "publish": [{"topic": "/rosout", "type": "rcl_interfaces/msg/Log"}]})
    procs = [JsonProc(fleetctl_argv("server", "--config", str(tmp_path / "server.yaml")), {},
                      tmp_path / "server.log")]
    try:
        wait_until(lambda: http_ok(f"http://127.0.0.1:{port}/healthz"), STARTUP_S,
                   describe="server")
        procs.append(JsonProc(fleetctl_argv("client", "--config", str(tmp_path / "alpha.yaml")),
                              {"ROS_DOMAIN_ID": str(DOMAIN_ID)}, tmp_path / "alpha.log"))
        wait_until(lambda: "alpha" in online_robots(f"http://127.0.0.1:{port}"), STARTUP_S,
                   describe="alpha online")
        yield port, procs[1]
    finally:
        for proc in reversed(procs):
            proc.stop()


@pytest.fixture
def logging_node() -> Iterator[None]:
    """A node publishing a log line every 50 ms with rcl's rosout QoS."""
    from rcl_interfaces.msg import Log
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    node = Node("planner", context=context)
    publisher = node.create_publisher(Log, "/rosout", QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    stop = threading.Event()

    def log_lines() -> None:
        k = 0
        while not stop.wait(0.05):  # the node's logging rate
            k += 1
            publisher.publish(Log(name="planner", msg=f"replanning ({k})"))

    thread = threading.Thread(target=log_lines, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(5)
        node.destroy_node()
        context.try_shutdown()


async def _frames(port: int, topic: str, count: int) -> list[bytes]:
    from websockets.asyncio.client import connect

    from fleetctl.wire.control import encode_subscription

    frames: list[bytes] = []
    async with connect(f"ws://127.0.0.1:{port}/", ping_interval=None, max_size=None,
                       additional_headers={"Authorization": f"Bearer {TOKEN}"}) as ws:
        await ws.send(encode_subscription(topic))
        async for message in ws:
            if isinstance(message, bytes):
                frames.append(message)
                if len(frames) >= count:
                    return frames
    raise AssertionError("the relay closed the connection")


def test_log_lines_reach_viewers_as_a_stream(fleet: tuple[int, JsonProc],
                                             logging_node: None) -> None:
    port, client = fleet
    # The client's 1 s refresh has matched the publishers' QoS (reliable, and before
    # 2026-12-06 transient-local): only frames after that say what it decided.
    wait_until(lambda: "/rosout: subscribed reliable" in client.stderr_tail(20_000),
               STARTUP_S, describe="the client matching /rosout's publishers")
    frames = asyncio.run(asyncio.wait_for(_frames(port, "/alpha/rosout", 10), STARTUP_S))
    metas = [read_metadata(f) for f in frames]
    assert {m.type for m in metas} == {"rcl_interfaces/msg/Log"}
    assert [m.latched for m in metas] == [False] * 10
    assert "transient-local" not in client.stderr_tail(20_000)
