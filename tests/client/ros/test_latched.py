"""Latched topics in the client's node: TRANSIENT_LOCAL in, latched frames out, and back
(real rclpy, real codec, a fake link port; ``ros`` is tests/client/ros/conftest.py's)."""

from __future__ import annotations

import contextlib
import dataclasses
import threading
from collections.abc import Iterator
from typing import Any

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

from fleetctl.client.config import parse_client_config  # noqa: E402
from fleetctl.client.ros.bridge import LATCHED_COMPRESS_BYTES, Bridge, LinkPort  # noqa: E402
from fleetctl.client.ros.executor import NodeExecutor  # noqa: E402
from fleetctl.client.ros.runner import status_encoder  # noqa: E402
from fleetctl.wire.codec import Codec  # noqa: E402
from fleetctl.wire.compression import COMPRESSED_TYPE, decompress  # noqa: E402
from fleetctl.wire.metadata import read_metadata  # noqa: E402
from fleetctl.wire.registry import TypeRegistry  # noqa: E402
from fleetctl.wire.samples import occupancy_grid  # noqa: E402
from tests.client.ros.test_bridge import FakePort, wait_for  # noqa: E402

pytestmark = pytest.mark.ros
DOMAIN_ID = 33  # this file's own ROS domain (the client tests use 20-39)
MAP_TYPE = "nav_msgs/msg/OccupancyGrid"
CONFIG = {
    "server_url": "ws://127.0.0.1:1/",
    "robot_name": "r1",
    "publish": [
        {"topic": "/map", "type": MAP_TYPE},
        {"topic": "/description", "type": "std_msgs/msg/String"},
    ],
    "subscribe": [
        {"remote_topic": "/r2/map", "type": MAP_TYPE, "local_topic": "/r2_map"},
        {"remote_topic": "/r2/.*", "type": "std_msgs/msg/String"},
    ],
    "status": {"period_s": 10.0},
}
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture(scope="module")
def codec() -> Codec:
    return Codec(TypeRegistry.default())


class ReconnectingPort(FakePort):
    """A fake port whose link reports its connections (``connects``), as the runner's."""

    def __init__(self) -> None:
        super().__init__()
        self.connects = 1

    def port(self) -> LinkPort:
        return dataclasses.replace(super().port(), connects=lambda: self.connects)


@contextlib.contextmanager
def running_bridge(context: Context, codec: Codec,
                   config: dict[str, Any] = CONFIG) -> Iterator[tuple[Bridge, ReconnectingPort]]:
    """The client's node on its own executor, as in ``fleetctl client``."""
    fake = ReconnectingPort()
    bridge = Bridge(parse_client_config(config), codec, codec.registry.typestore, fake.port(),
                    status_encoder(codec, "r1"), context=context)
    executor = NodeExecutor(bridge, context)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        yield bridge, fake
    finally:
        executor.shutdown()
        thread.join(5)
        bridge.destroy_node()


def map_cdr(codec: Codec, size: int) -> bytes:
    grid = occupancy_grid(codec.registry, size)
    return bytes(codec.registry.typestore.serialize_cdr(grid, MAP_TYPE))


def sent_on(fake: FakePort, topic: str) -> list[bytes]:
    with fake.lock:
        return [frame for spec, frame in fake.sent if spec.remote_topic == topic]


def test_map_published_before_the_client_starts_arrives_latched_and_compressed(
    ros: tuple[Context, Node], codec: Codec
) -> None:
    context, peer = ros
    publisher = peer.create_publisher(_map_class(), "/map", LATCHED)
    publisher.publish(map_cdr(codec, 384))  # 147 KB: nobody listens yet
    with running_bridge(context, codec) as (bridge, fake):
        frame = wait_for(lambda: sent_on(fake, "/r1/map") and sent_on(fake, "/r1/map")[0])
        map_input = bridge.inputs[0]
        assert map_input.latched and map_input.reliable
        meta = read_metadata(frame)
        # Larger than 64 KiB and the entry says compression none: deflate, still latched.
        assert (meta.type, meta.latched) == (COMPRESSED_TYPE, True)
        assert len(frame) < 20_000
        inner, grid = codec.decode(decompress(frame, 1 << 24))
        assert (inner.type, inner.latched, grid.info.width) == (MAP_TYPE, True, 384)
        assert bridge.stats.latched_sent == 1 and bridge.stats.latched_compressed == 1
        # Kept for the next connection: offered again when the link reconnects.
        fake.connects += 1
        wait_for(lambda: len(sent_on(fake, "/r1/map")) == 2)
        assert sent_on(fake, "/r1/map")[-1] is frame and bridge.stats.latched_resent == 1


def test_latched_publisher_appearing_after_the_client_is_matched(
    ros: tuple[Context, Node], codec: Codec
) -> None:
    from std_msgs.msg import String

    context, peer = ros
    with running_bridge(context, codec) as (bridge, fake):
        publisher = peer.create_publisher(String, "/description", LATCHED)
        publisher.publish(String(data="<robot name='r1'/>"))

        def latched_frame() -> bytes | None:
            frames = sent_on(fake, "/r1/description")
            return next((f for f in frames if read_metadata(f).latched), None)

        frame = wait_for(latched_frame)
        meta, msg = codec.decode(frame)
        assert msg.data == "<robot name='r1'/>"
        assert len(frame) < LATCHED_COMPRESS_BYTES and meta.type == "std_msgs/msg/String"
        assert bridge.inputs[1].latched
        # The volatile reader may have matched the publisher first and got the message
        # live (unmarked) before the switch: at most that one copy comes before.
        assert len(sent_on(fake, "/r1/description")) <= 2


def test_a_volatile_publisher_beside_makes_the_topic_volatile_again(
    ros: tuple[Context, Node], codec: Codec
) -> None:
    from std_msgs.msg import String

    context, peer = ros
    with running_bridge(context, codec) as (bridge, fake):
        latched = peer.create_publisher(String, "/description", LATCHED)
        latched.publish(String(data="v1"))
        wait_for(lambda: sent_on(fake, "/r1/description"))
        volatile = peer.create_publisher(String, "/description", 10)
        wait_for(lambda: not bridge.inputs[1].latched)
        wait_for(lambda: volatile.get_subscription_count() > 0)
        before = len(sent_on(fake, "/r1/description"))
        volatile.publish(String(data="v2"))
        frame = wait_for(lambda: sent_on(fake, "/r1/description")[before:]
                         and sent_on(fake, "/r1/description")[-1])
        meta, msg = codec.decode(frame)
        assert (msg.data, meta.latched) == ("v2", False)
        # The last message is not latched: nothing stale is re-sent on a reconnect.
        assert bridge.resend_latched() == 0


def test_received_latched_frame_is_republished_transient_local(
    ros: tuple[Context, Node], codec: Codec
) -> None:
    from std_msgs.msg import String

    context, peer = ros
    with running_bridge(context, codec) as (bridge, _fake):
        grid = occupancy_grid(codec.registry, 64)
        bridge.deliver(codec.encode(grid, MAP_TYPE, "/r2/map", latched=True))
        bridge.deliver(codec.encode(String(data="plain"), "std_msgs/msg/String", "/r2/chat"))
        bridge.deliver(codec.encode(String(data="urdf"), "std_msgs/msg/String", "/r2/urdf",
                                    latched=True))
        assert bridge.stats.latched_republished == 2
        # Subscribers created after the publish: only a transient-local publisher has it.
        maps: list[Any] = []
        urdfs: list[Any] = []
        peer.create_subscription(_map_class(), "/r2_map", maps.append, LATCHED)
        peer.create_subscription(String, "/r2/urdf", urdfs.append, LATCHED)
        wait_for(lambda: maps and urdfs)
        assert maps[0].info.width == 64 and urdfs[0].data == "urdf"
        infos = peer.get_publishers_info_by_topic("/r2/chat")
        assert [i.qos_profile.durability for i in infos] == [DurabilityPolicy.VOLATILE]


def test_a_later_volatile_frame_goes_through_the_latched_publisher(
    ros: tuple[Context, Node], codec: Codec
) -> None:
    from std_msgs.msg import String

    context, peer = ros
    with running_bridge(context, codec) as (bridge, _fake):
        bridge.deliver(codec.encode(String(data="old"), "std_msgs/msg/String", "/r2/x",
                                    latched=True))
        bridge.deliver(codec.encode(String(data="new"), "std_msgs/msg/String", "/r2/x"))
        got: list[Any] = []
        peer.create_subscription(String, "/r2/x", got.append, LATCHED)
        wait_for(lambda: got)
        # One publisher per topic, depth 1: a late joiner gets the last message only.
        assert [m.data for m in got] == ["new"]
        assert len(peer.get_publishers_info_by_topic("/r2/x")) == 1


def _map_class() -> Any:
    from nav_msgs.msg import OccupancyGrid

    return OccupancyGrid
