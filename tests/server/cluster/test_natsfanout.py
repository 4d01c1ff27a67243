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


async def test_a_replica_that_cannot_read_the_stream_gets_recent_and_next_no_drop_frames(
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
        fan.publish("/r/events", b"e2", True, None)
        fan.publish("/r/pose", b"p1", False, None)
        await wait_until(lambda: len(nats.sent) == 1, 5.0)
        assert nats.sent == [("fleetctl.r.pose", b"p1")]  # no_drop: through the stream only
        assert [q.order for q in sessions._queue] == [f"{epoch}:1:0", f"{epoch}:2:1"]
        # B cannot read the stream: what A's senders sent lately, then the next ones, with
        # their digests and orders (B drops what it had, and delivers in order).
        await fan._reader_away_received(Msg(b"relay-b"))  # type: ignore[arg-type]
        fan.publish("/r/events", b"e3", True, None)
        await wait_until(lambda: len(nats.sent) == 4, 5.0)
        assert nats.sent[1:] == [("fleetctl.r.events", b"e1"), ("fleetctl.r.events", b"e2"),
                                 ("fleetctl.r.events", b"e3")]
        assert nats.headers[1:] == [
            {"Fleetctl-Digest": frame_digest(f), "Fleetctl-Order": order}
            for f, order in ((b"e1", f"{epoch}:1:0"), (b"e2", f"{epoch}:2:1"),
                             (b"e3", f"{epoch}:3:2"))]
        assert fan.replays == 1
        await fan._reader_away_received(Msg(b"relay-b"))  # said again: no second replay
        assert fan.replays == 1
        await fan._reader_away_received(Msg(b"relay-a"))  # our own name: ignored
        # It stops saying so: after the hold, no_drop frames take the stream only again.
        fan._readers_away["relay-b"] = 0.0  # its last "cannot" older than the hold
        fan.publish("/r/events", b"e4", True, None)
        fan.publish("/r/pose", b"p2", False, None)
        await wait_until(lambda: len(nats.sent) == 5, 5.0)
        assert nats.sent[-1] == ("fleetctl.r.pose", b"p2")
    finally:
        task.cancel()
