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


class FakeNats:
    """The two things the publish loop uses of nats-py's client (a unit test's stand-in:
    the real client is tested in test_replicas.py)."""

    def __init__(self) -> None:
        self.is_connected = False
        self.sent: list[tuple[str, bytes]] = []
        self.headers: list[dict[str, str] | None] = []

    async def publish(self, subject: str, payload: bytes,
                      headers: dict[str, str] | None = None) -> None:
        self.sent.append((subject, payload))
        self.headers.append(headers)


async def test_nats_away_sheds_latest_only_and_keeps_no_drop_in_order() -> None:
    import asyncio

    from tests.support import wait_until

    config = ClusterConfig(name="a", nats_urls=("nats://127.0.0.1:4222",))
    fan = NatsFanout(Recorder(), lambda frame: None, config)  # type: ignore[arg-type]
    nats = FakeNats()
    fan._nc = nats  # type: ignore[assignment]
    task = asyncio.create_task(fan._publish_loop())
    try:
        fan.publish("/r/pose", b"p1", False, None)
        fan.publish("/r/events", b"e1", True, None)
        fan.publish("/r/pose", b"p2", False, None)
        fan.publish("/r/events", b"e2", True, None)
        await wait_until(lambda: fan.dropped.get("disconnected") == 2, 5.0)
        assert [q.frame for q in fan._queue] == [b"e1", b"e2"]
        nats.is_connected = True
        fan._back.set()  # what the reconnect callback does
        await wait_until(lambda: len(nats.sent) == 2, 5.0)
        assert nats.sent == [("fleetctl.r.events", b"e1"), ("fleetctl.r.events", b"e2")]
        assert fan.published == 2 and fan._queue.bytes == 0
    finally:
        task.cancel()


class Msg:
    def __init__(self, data: bytes) -> None:
        self.data = data


async def test_no_drop_frames_cross_at_once_with_their_digest_and_order_and_again_for_a_reader_away(
) -> None:
    import asyncio

    from fleetctl.server.cluster.framequeue import frame_digest
    from fleetctl.server.cluster.sharedsessions import SharedSessions
    from tests.support import wait_until

    config = ClusterConfig(name="relay-a", nats_urls=("nats://127.0.0.1:4222",))
    sessions = SharedSessions(config, 3600.0)
    fan = NatsFanout(Recorder(), lambda frame: None, config,  # type: ignore[arg-type]
                     sessions=sessions)
    nats = FakeNats()
    nats.is_connected = True
    fan._nc = sessions._nc = nats  # type: ignore[assignment]
    epoch = sessions.order.epoch
    task = asyncio.create_task(fan._publish_loop())
    try:
        fan.publish("/r/events", b"e1", True, None)
        fan.publish("/r/pose", b"p1", False, None)
        fan.publish("/r/events", b"e2", True, None)
        await wait_until(lambda: len(nats.sent) == 3, 5.0)
        # Over core NATS at once, and queued for the stream too.
        assert nats.sent == [("fleetctl.r.events", b"e1"), ("fleetctl.r.pose", b"p1"),
                             ("fleetctl.r.events", b"e2")]
        assert nats.headers == [
            {"Fleetctl-Digest": frame_digest(b"e1"), "Fleetctl-Order": f"{epoch}:1:0"},
            None,
            {"Fleetctl-Digest": frame_digest(b"e2"), "Fleetctl-Order": f"{epoch}:2:1"}]
        assert [q.frame for q in sessions._queue] == [b"e1", b"e2"]
        assert [q.order for q in sessions._queue] == [f"{epoch}:1:0", f"{epoch}:2:1"]
        # B cannot read the stream: what A's senders sent lately comes again, same
        # digests and orders (B drops what it had).
        await fan._reader_away_received(Msg(b"relay-b"))  # type: ignore[arg-type]
        await wait_until(lambda: len(nats.sent) == 5, 5.0)
        assert nats.sent[3:] == [("fleetctl.r.events", b"e1"), ("fleetctl.r.events", b"e2")]
        assert nats.headers[3:] == nats.headers[0:3:2]
        assert fan.replays == 1
        await fan._reader_away_received(Msg(b"relay-b"))  # said again: no second replay
        await fan._reader_away_received(Msg(b"relay-a"))  # our own name: ignored
        assert fan.replays == 1 and len(nats.sent) == 5
    finally:
        task.cancel()
