"""The client's local subscriptions (fleetctl.client.ros.qos) with real rclpy publishers:
what DDS loses before the client takes it is counted (fleetctl.client.seqgaps)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import Iterator
from typing import Any

import pytest

pytest.importorskip("rclpy")

from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from fleetctl.client.config import parse_client_config
from fleetctl.client.ros.bridge import Bridge, LinkPort
from fleetctl.client.ros.intake import LoopIntake, load_wakeups
from fleetctl.client.ros.runner import status_encoder
from fleetctl.waiting import wait_until
from fleetctl.wire.codec import Codec
from fleetctl.wire.registry import TypeRegistry
from tests.client.ros.harness import spun_bridge
from tests.support import ros_domain_alone

pytestmark = pytest.mark.ros
# This file's own ROS domain (90: outside every benchmark's range too; it was 73, which a
# soak_client run may take), or a spare one while another run of this file holds it: the
# burst tests count gaps only with one publisher on the topic (fleetctl.client.seqgaps),
# and the last one needs a /scan nobody publishes.
DOMAIN_ID = ros_domain_alone(90)
BURST = 10_000
DEADLINE_S = 30.0
# A driver's reliable writer with a short KEEP_LAST history: a burst faster than the
# client takes it overwrites what the client has not taken yet.
SHORT_HISTORY = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


class _Taker:
    """The link's send, which keeps the text of every message the bridge hands it and, once
    :meth:`hold` is called, holds the thread that took the next one until :meth:`release`.

    A burst published while that thread is held must overflow the reader's history, so the
    loss the tests count is there by construction. Without the hold they depended on the
    taking thread falling behind a 10,000-message burst, and it sometimes kept up (a CI
    failure of 1c79c66: "the burst lost nothing", with Python's default GIL interval too).
    """

    def __init__(self) -> None:
        self.texts: list[str] = []
        self.holding = threading.Event()
        self._codec = Codec(TypeRegistry.default())
        self._armed = False
        self._released = threading.Event()

    def __call__(self, spec: Any, frame: bytes, published_ns: int) -> None:
        self.texts.append(str(self._codec.decode(frame)[1].data))
        if self._armed and not self._released.is_set():
            self.holding.set()
            self._released.wait(DEADLINE_S)

    def hold(self) -> None:
        self._armed = True

    def release(self) -> None:
        self._released.set()


def _burst_through(bridge: Bridge, publisher: Any, taker: _Taker) -> None:
    """Publish one message at a time until the bridge took one and the taking thread is
    held, then BURST at once, release it, and wait until the bridge took the last (a
    KEEP_LAST writer keeps its newest)."""
    count = 0

    def publish_one() -> None:
        nonlocal count
        count += 1
        publisher.publish(String(data=str(count)))

    def taken_one() -> bool:
        publish_one()
        return bridge.stats.local_in > 0

    wait_until(taken_one, DEADLINE_S, poll_s=0.05, describe="the bridge took a message")
    taker.hold()

    def held() -> bool:
        publish_one()
        return taker.holding.is_set()

    wait_until(held, DEADLINE_S, poll_s=0.05, describe="the taking thread held")
    try:
        for _ in range(BURST):
            publish_one()
    finally:
        taker.release()
    wait_until(lambda: taker.texts and taker.texts[-1] == str(count), DEADLINE_S,
               describe=f"message {count} taken")


@contextlib.contextmanager
def _texts_bridge(context: Any, topic: str) -> Iterator[tuple[Bridge, _Taker]]:
    taker = _Taker()
    with spun_bridge(context, {"topic": topic, "type": "std_msgs/msg/String",
                               "no_drop": True}, send=taker) as bridge:
        yield bridge, taker


def _assert_counted(bridge: Bridge, topic: str, texts: list[str]) -> None:
    taken = [int(text) for text in texts]
    missing = taken[-1] - taken[0] + 1 - len(taken)
    assert missing > 0, "the burst lost nothing: no loss to count"
    assert bridge.stats.lost_before_client == missing
    assert bridge.stats.per_topic_lost == {topic: missing}
    assert bridge.stats.local_in == len(taken)
    (subscription,) = bridge.inputs
    assert subscription.gaps.lost == missing


def test_a_burst_dds_drops_before_the_executor_takes_it_is_counted(
        ros: tuple[Any, Any], caplog: pytest.LogCaptureFixture) -> None:
    """20,000 no_drop messages published in 1.5 s reached the relay as 2,597 and nothing
    said so: DDS overwrote the rest before the client took them."""
    context, peer = ros
    with _texts_bridge(context, "/burst") as (bridge, taker):
        assert not bridge.inputs[0].loop_served  # the client's executor takes it
        _burst_through(bridge, peer.create_publisher(String, "/burst", SHORT_HISTORY), taker)
    _assert_counted(bridge, "/burst", taker.texts)
    said = [r.getMessage() for r in caplog.records if "lost before this client" in r.message]
    assert said and said[0].startswith("/burst: ") and "no_drop messages" in said[0]
    assert "DDS keeps only the last 1000 messages here" in said[0]


def test_a_burst_lost_before_the_loop_intake_takes_it_is_counted(
        ros: tuple[Any, Any]) -> None:
    """The same on the loop thread's intake (fleetctl.client.ros.intake), which takes the
    uncompressed topics of ``fleetctl client``."""
    wakeups = load_wakeups()
    if wakeups is None:
        pytest.skip("no new-message callbacks on this platform")
    context, peer = ros

    async def scenario() -> None:
        intake = LoopIntake(asyncio.get_running_loop(), wakeups)
        codec = Codec(TypeRegistry.default())
        taker = _Taker()
        port = LinkPort(admit=lambda topic: True, send_status=lambda frame: None,
                        send=taker)
        config = parse_client_config({
            "server_url": "ws://127.0.0.1:1/", "robot_name": "r1",
            "publish": [{"topic": "/burst_loop", "type": "std_msgs/msg/String",
                         "no_drop": True}]}, source="test.yaml")
        bridge = Bridge(config, codec, codec.registry.typestore, port,
                        status_encoder(codec, "r1"), context=context, intake=intake)
        try:
            assert bridge.inputs[0].loop_served
            publisher = peer.create_publisher(String, "/burst_loop", SHORT_HISTORY)
            await asyncio.to_thread(_burst_through, bridge, publisher, taker)
            _assert_counted(bridge, "/burst_loop", taker.texts)
        finally:
            intake.close()
            bridge.destroy_node()

    asyncio.run(scenario())


def test_a_topic_nobody_publishes_is_explained_once_naming_the_namespaced_one(
        ros: tuple[Any, Any], caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A namespaced driver publishes /husky1/scan, the entry says /scan: nothing was ever
    sent and nothing was said, for as long as the client ran."""
    from sensor_msgs.msg import LaserScan

    from fleetctl.client.ros import qos

    context, peer = ros
    caplog.set_level(logging.INFO, "fleetctl.client.ros.qos")
    with spun_bridge(context, {"topic": "/scan", "type": "sensor_msgs/msg/LaserScan"}) as bridge:
        peer.create_publisher(LaserScan, "/husky1/scan", 10)  # the node keeps it
        wait_until(lambda: bridge.count_publishers("/husky1/scan") > 0, DEADLINE_S,
                   describe="the bridge sees the driver")
        monkeypatch.setattr(qos, "NO_PUBLISHER_WARN_S", 0.0)  # the next refresh (<= 1 s)

        def said(text: str) -> list[str]:
            return [r.getMessage() for r in caplog.records if text in r.getMessage()]

        wait_until(lambda: said("no publisher in"), DEADLINE_S, describe="the explanation")
        assert said("no publisher in")[0].startswith("/scan: no publisher in ")
        assert said("no publisher in")[0].endswith(
            "so nothing of it is sent; the ROS graph has /husky1/scan "
            "(sensor_msgs/msg/LaserScan): a namespaced or remapped driver? set this entry's "
            "topic to the one it publishes")
        peer.create_publisher(LaserScan, "/scan", 10)
        wait_until(lambda: said("a publisher appeared after"), DEADLINE_S,
                   describe="the publisher's arrival")
        assert len(said("no publisher in")) == 1
