"""The client's node sends ``<remote_topic>/viewer`` beside a cloud with ``viewer_cloud:``
(real rclpy publisher, real codec, a fake link port; ``ros`` is this folder's conftest's)."""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402

from fleetctl.client.config import PublishSpec, parse_client_config  # noqa: E402
from fleetctl.client.ros.bridge import Bridge  # noqa: E402
from fleetctl.client.ros.executor import NodeExecutor  # noqa: E402
from fleetctl.client.ros.runner import status_encoder  # noqa: E402
from fleetctl.client.viewercloud import VIEWER_CLOUD_TYPE, decode, encode  # noqa: E402
from fleetctl.wire.codec import Codec  # noqa: E402
from fleetctl.wire.compression import COMPRESSED_TYPE, decompress  # noqa: E402
from fleetctl.wire.metadata import read_metadata  # noqa: E402
from fleetctl.wire.registry import TypeRegistry  # noqa: E402
from tests.client.ros.test_bridge import FakePort, wait_for  # noqa: E402

pytestmark = pytest.mark.ros
DOMAIN_ID = 32  # this file's own ROS domain (the client tests use 20-39)
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
CONFIG = {
    "server_url": "ws://127.0.0.1:1/",
    "robot_name": "r1",
    "publish": [
        {"topic": "/points", "type": CLOUD_TYPE, "priority": 3, "viewer_cloud": {}},
        {"topic": "/flat", "type": CLOUD_TYPE, "viewer_cloud": {"resolution_m": 0.05}},
        {"topic": "/plain", "type": CLOUD_TYPE},
    ],
    "status": {"period_s": 10.0},
}


@pytest.fixture(scope="module")
def codec() -> Codec:
    return Codec(TypeRegistry.default())


@contextlib.contextmanager
def running_bridge(context: Context, codec: Codec) -> Iterator[tuple[Bridge, FakePort]]:
    """The client's node on its own executor, as in ``fleetctl client``."""
    fake = FakePort()
    bridge = Bridge(parse_client_config(CONFIG), codec, codec.registry.typestore, fake.port(),
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


def cloud(codec: Codec, fields: str = "xyz", n: int = 4000) -> Any:
    """A 16-byte-point cloud (x y z rgb, or the given float fields) of a noisy plane."""
    reg = codec.registry
    rng = np.random.default_rng(1)
    points = np.zeros((n, 4), np.float32)
    points[:, :2] = rng.uniform(-1.0, 1.0, (n, 2))
    points[:, 2] = 2.0 + rng.normal(0.0, 0.004, n)
    points[:, 3] = rng.integers(0, 1 << 24, n, dtype=np.uint32).view(np.float32)
    field_cls = reg.get("sensor_msgs/msg/PointField").cls
    names = [*fields, "rgb"]
    header = reg.get("std_msgs/msg/Header").cls(
        reg.get("builtin_interfaces/msg/Time").cls(7, 0), "camera")
    return reg.get(CLOUD_TYPE).cls(
        header, 1, n, [field_cls(name, 4 * i, 7, 1) for i, name in enumerate(names)],
        False, 16, 16 * n, points.view(np.uint8).reshape(-1), True)


def sent_on(fake: FakePort, topic: str) -> list[tuple[PublishSpec, bytes]]:
    with fake.lock:
        return [(spec, frame) for spec, frame in fake.sent if spec.remote_topic == topic]


def publish_until(publisher: Any, cdr: bytes, done: Any) -> Any:
    """Publish (volatile: until the client's subscription matched) until *done* holds."""
    return wait_for(lambda: done() or publisher.publish(cdr))


def test_a_viewer_cloud_is_sent_deflated_beside_the_unchanged_full_cloud(
    ros: tuple[Context, Node], codec: Codec
) -> None:
    from sensor_msgs.msg import PointCloud2

    context, peer = ros
    msg = cloud(codec)
    cdr = bytes(codec.registry.typestore.serialize_cdr(msg, CLOUD_TYPE))
    with running_bridge(context, codec) as (bridge, fake):
        publisher = peer.create_publisher(PointCloud2, "/points", 10)
        (spec, frame), *_ = publish_until(publisher, cdr,
                                          lambda: sent_on(fake, "/r1/points/viewer"))
        assert read_metadata(frame).type == COMPRESSED_TYPE
        meta, viewer = codec.decode(decompress(frame, 1 << 24, frame_codec=codec))
        assert (meta.type, meta.topic) == (VIEWER_CLOUD_TYPE, "/r1/points/viewer")
        assert (spec.priority, spec.no_drop, spec.type) == (3, False, VIEWER_CLOUD_TYPE)
        expected = encode(msg, 0.01)
        np.testing.assert_array_equal(viewer.xyz, expected.xyz)
        np.testing.assert_array_equal(viewer.rgb, expected.rgb)
        assert viewer.header.frame_id == "camera" and len(decode(viewer)[0]) > 1000
        # The full cloud went too, exactly as published.
        (_, full), *_ = sent_on(fake, "/r1/points")
        full_meta, full_msg = codec.decode(full)
        assert full_meta.type == CLOUD_TYPE
        np.testing.assert_array_equal(full_msg.data, msg.data)
        assert bridge.viewer_clouds.stats.clouds >= 1
        assert bridge.viewer_clouds.stats.errors == 0


def test_a_cloud_without_z_is_relayed_in_full_and_logged_once(
    ros: tuple[Context, Node], codec: Codec, caplog: pytest.LogCaptureFixture
) -> None:
    from sensor_msgs.msg import PointCloud2

    context, peer = ros
    cdr = bytes(codec.registry.typestore.serialize_cdr(cloud(codec, "xy"), CLOUD_TYPE))
    good = bytes(codec.registry.typestore.serialize_cdr(cloud(codec), CLOUD_TYPE))
    with caplog.at_level(logging.WARNING, logger="fleetctl.client.viewercloud"), \
            running_bridge(context, codec) as (bridge, fake):
        flat = peer.create_publisher(PointCloud2, "/flat", 10)
        plain = peer.create_publisher(PointCloud2, "/plain", 10)
        publish_until(flat, cdr, lambda: len(sent_on(fake, "/r1/flat")) >= 3)
        # An entry without viewer_cloud: only the full cloud.
        publish_until(plain, good, lambda: sent_on(fake, "/r1/plain"))
    assert not sent_on(fake, "/r1/flat/viewer") and not sent_on(fake, "/r1/plain/viewer")
    assert bridge.viewer_clouds.stats.errors >= 3
    warnings = [r.getMessage() for r in caplog.records
                if r.name == "fleetctl.client.viewercloud"]
    assert len(warnings) == 1
    assert "/flat" in warnings[0] and "no z field" in warnings[0]
