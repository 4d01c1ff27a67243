"""NatsFanout without a NATS server: local delivery first, the bounded publish queue."""

from __future__ import annotations

from typing import Any

from fleetctl.server.cluster.config import ClusterConfig
from fleetctl.server.cluster.natsfanout import NatsFanout


class Recorder:
    def __init__(self) -> None:
        self.frames: list[tuple[str, bytes]] = []

    def publish(self, topic: str, frame: bytes, no_drop: bool, message_id: Any) -> None:
        self.frames.append((topic, frame))


def test_queue_bounded_and_drops_counted_local_delivery_unaffected() -> None:
    local = Recorder()
    config = ClusterConfig(name="a", nats_urls=("nats://127.0.0.1:4222",),
                           publish_queue_frames=2, publish_queue_bytes=1000)
    fan = NatsFanout(local, lambda frame: None, config)  # type: ignore[arg-type]
    for _ in range(5):
        fan.publish("/r/t", b"x" * 10, False, None)
    fan.publish("/r/big", b"x" * 2000, False, None)  # past the byte bound
    assert len(local.frames) == 6  # every frame delivered locally
    assert fan.dropped == {"queue_full": 4}
    families = {name: values for name, _, _, _, values in fan.metric_families()}
    assert families["fleetctl_cluster_dropped_total"] == {"queue_full": 4.0}
    assert families["fleetctl_cluster_connected"] == {"": 0.0}
