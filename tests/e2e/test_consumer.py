"""The e2e consumer against a real relay: every frame recorded once, in order, with its
receipt time taken in the read (fleetctl.frame_sink)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest
from websockets.asyncio.client import connect

from fleetctl.e2e import consumer, payloads
from fleetctl.e2e.samples import load
from fleetctl.wire.codec import default_codec
from tests.client.conftest import OPERATOR_TOKEN, ROBOT_TOKEN, make_server
from tests.support import wait_until, watch_reads

POSE = "geometry_msgs/msg/PoseStamped"


def test_the_consumer_records_every_frame_once_in_order(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    # Watch where frames are recorded: inside the connection's data_received (the sink)
    # or later, from the reader's recv() path.
    reading = watch_reads(monkeypatch, consumer.ConsumerConnection)
    in_read: list[bool] = []
    real_feed = consumer.Recorder.feed

    def feed(self: consumer.Recorder, frame: bytes, recv_time_ns: int) -> object:
        in_read.append(reading())
        return real_feed(self, frame, recv_time_ns)

    monkeypatch.setattr(consumer.Recorder, "feed", feed)
    codec = default_codec()
    ts = codec.registry.typestore
    count = 200

    async def main() -> None:
        async with make_server(tmp_path) as srv:
            url = f"ws://127.0.0.1:{srv.port}/"
            task = asyncio.create_task(consumer.consume(
                [url], OPERATOR_TOKEN, "/r1/.*", "c0", tmp_path))
            await wait_until(lambda: (tmp_path / "c0.ready").exists(), 10.0)
            async with connect(url, additional_headers={"Authorization": f"Bearer {ROBOT_TOKEN}"},
                               compression=None) as robot:
                for seq in range(1, count + 1):
                    msg = payloads.build(ts, POSE, 0, seq, time.time_ns())
                    await robot.send(codec.encode(msg, POSE, "/r1/pose", no_drop=True,
                                                  seq=seq))
                    if seq % 50 == 0:  # some frames alone in a read, some many in one
                        await asyncio.sleep(0.01)

                def recorded() -> int:
                    return len((tmp_path / "c0.jsonl").read_text().splitlines())

                await wait_until(lambda: recorded() == count, 10.0)
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    asyncio.run(main())
    samples = list(load((tmp_path / "c0.jsonl").read_text()))
    assert len(in_read) == count and all(in_read)
    assert [s.seq for s in samples] == list(range(1, count + 1))
    assert all(s.topic == "/r1/pose" and s.consumer == "c0" for s in samples)
    assert all(0 <= s.latency_ms < 5000 for s in samples)
