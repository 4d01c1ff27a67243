"""RobotLink against the real relay server over real WebSocket connections (loopback)."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import socket
from pathlib import Path
from typing import Any

import pytest

from fleetctl.client.linktuning import LinkTuning
from fleetctl.client.scheduler import SchedulerConfig
from fleetctl.client.slowdeflate import SlowDeflateSettings
from fleetctl.client.transport import LinkConnection, RobotLink, backoff_delay_s
from fleetctl.server.app import RelayServer
from fleetctl.wire import samples
from fleetctl.wire.codec import default_codec
from fleetctl.wire.fragments import split
from tests.client.conftest import (
    ROBOT_TOKEN,
    Consumer,
    TcpForwarder,
    make_server,
    robot_config,
    running,
    wait_until,
)
from tests.support import ManualClock, decode_text, string_frame, watch_reads

FAST = LinkTuning(keepalive_interval_s=0.1, link_timeout_s=0.6, open_timeout_s=1.0)


def url_of(port: int) -> str:
    return f"ws://127.0.0.1:{port}/"


async def test_no_drop_and_fragmented_messages_arrive_in_order(
    server: RelayServer, tmp_path: Path
) -> None:
    cfg = robot_config(server.url, tmp_path, limits={"max_fragment_bytes": 4096})
    big = "x" * 300_000
    async with Consumer.open(server.url, "/r1/.*") as consumer, running(
        RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
    ) as link:
        for i in range(200):
            link.offer("/r1/events", string_frame("/r1/events", f"e{i}", no_drop=True, seq=i + 1),
                       priority=1.0, no_drop=True)
        link.offer("/r1/big", string_frame("/r1/big", big), priority=1.0, no_drop=False)
        await wait_until(lambda: len(consumer.frames) >= 201)
        assert consumer.texts("/r1/events") == [f"e{i}" for i in range(200)]
        assert consumer.texts("/r1/big") == [big]
        await wait_until(lambda: link.stats()["in_flight_bytes"] == 0)
        stats = link.stats()
        assert stats["topics"]["/r1/events"]["acked"] == 200
        assert stats["topics"]["/r1/big"]["sent_frames"] > 70  # 300 kB / 4 kB fragments
        assert stats["identities"] == ["r1"]
        assert stats["min_rtt_ms"] is not None


async def test_on_a_slow_link_fragments_of_large_messages_are_deflated_too(
    server: RelayServer, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The slow-link rule (fleetctl.client.slowdeflate) forced on, every rate counting as
    slow: once the link has a rate, a large message goes as deflated fragments through the
    real relay and arrives whole and unchanged."""
    cfg = robot_config(server.url, tmp_path, limits={"max_fragment_bytes": 4096})
    always = SlowDeflateSettings(on_below_Bps=1e15, off_above_Bps=1e15, on_after_s=0.0)
    tuning = dataclasses.replace(FAST, slow_deflate=always)
    big = "x" * 300_000
    caplog.set_level(logging.INFO, logger="fleetctl.client.link")
    async with Consumer.open(server.url, "/r1/.*") as consumer, running(
        RobotLink(cfg, on_frame=lambda f: None, tuning=tuning)
    ) as link:
        for i in range(20):  # the link learns a rate (64 KB: more than a small message)
            link.offer("/r1/warm", string_frame("/r1/warm", f"{i}" * 64_000, seq=i + 1),
                       priority=1.0, no_drop=True)
        await wait_until(lambda: link.stats()["uplink_deflate"]["all_messages"])
        link.offer("/r1/big", string_frame("/r1/big", big), priority=1.0, no_drop=False)
        await wait_until(lambda: consumer.texts("/r1/big") == [big])
        await wait_until(lambda: link.stats()["in_flight_bytes"] == 0)
        stats = link.stats()
        assert stats["topics"]["/r1/big"]["sent_frames"] > 70  # 4 kB fragments
        deflate = stats["uplink_deflate"]
        assert deflate["negotiated"] and deflate["switches"] == 1
        # 300 kB of one letter: the fragments went deflated (raw, the share stays ~1).
        assert deflate["wire_share"] < 0.3
        # What a producer adapting to the link (the video) is told, to count on the wire.
        assert link.feedback("/r1/big").topic.wire_share == pytest.approx(deflate["wire_share"],
                                                                  abs=1e-4)
    said = [r.getMessage() for r in caplog.records if "on the wire" in r.getMessage()]
    assert len(said) == 1 and "deflating every message" in said[0], said


async def test_on_a_slow_link_deflated_fragments_fill_the_path_s_segments(
    server: RelayServer, tmp_path: Path
) -> None:
    """Through a path whose segments carry 1188 bytes (the forwarder clamps the MSS, as a
    smaller MTU does), the slow-link rule forced on: a camera's images (random bytes) go
    in fragments sized to fill one segment once deflated
    (fleetctl.client.segmentfill), and arrive whole through the real relay."""
    forwarder = TcpForwarder(server.port, mss=1200)
    await forwarder.accept()
    cfg = robot_config(url_of(forwarder.port), tmp_path, limits={"max_fragment_bytes": 2048})
    always = SlowDeflateSettings(on_below_Bps=1e15, off_above_Bps=1e15, on_after_s=0.0)
    tuning = dataclasses.replace(FAST, slow_deflate=always)
    codec = default_codec()
    images = [codec.encode(samples.compressed_image(codec.registry, 60_000, seed=i),
                           "sensor_msgs/msg/CompressedImage", "/r1/image", seq=100 + i)
              for i in range(4)]
    try:
        async with Consumer.open(server.url, "/r1/image") as consumer, running(
            RobotLink(cfg, on_frame=lambda f: None, tuning=tuning)
        ) as link:
            for i in range(20):  # the link learns a rate and starts deflating everything
                link.offer("/r1/warm", string_frame("/r1/warm", f"{i}" * 64_000, seq=i + 1),
                           priority=1.0, no_drop=True)
            await wait_until(lambda: link.stats()["uplink_deflate"]["all_messages"])
            for n, image in enumerate(images, 1):  # each split by what the last taught
                link.offer("/r1/image", image, priority=1.0, no_drop=True)

                def acked(count: int = n) -> bool:
                    return bool(link.stats()["topics"]["/r1/image"]["acked"] == count)

                await wait_until(acked)
            await wait_until(lambda: len(consumer.frames) == len(images))
            assert consumer.frames == images
            share = link.stats()["uplink_deflate"]["fragment_payload_bytes"]["/r1/image"]
            # The segment's room: 1188 less the WebSocket header, the slack and ~15-70
            # bytes of deflated metadata; not the 2048 - 256 the bound would allow.
            assert share is not None and 1188 - 100 < share < 1188 - 20, share
            assert link.stats()["topics"]["/r1/image"]["sent_frames"] >= 4 * 60_000 // share
    finally:
        await forwarder.refuse()


async def test_robot_receives_commands_reassembled_and_subscribes(
    server: RelayServer, tmp_path: Path
) -> None:
    received: list[bytes] = []
    cfg = robot_config(server.url, tmp_path)
    async with Consumer.open(server.url) as operator, running(
        RobotLink(cfg, on_frame=received.append, tuning=FAST)
    ) as link:
        await wait_until(lambda: link.stats()["subscribed"] == ["/r1/cmd.*"])
        await operator.ws.send(string_frame("/r1/cmd", "go"))
        large = string_frame("/r1/cmd_big", "y" * 100_000)
        for fragment in split(large, topic="/r1/cmd_big", message_id=7,
                              max_fragment_bytes=8192, no_drop=False):
            await operator.ws.send(fragment)
        await wait_until(lambda: len(received) == 2)
        assert [decode_text(f) for f in received] == ["go", "y" * 100_000]
        assert link.stats()["received"]["reassembly"]["completed"] == 1


async def test_commands_reach_on_frame_in_the_read_that_brought_them(
    server: RelayServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A binary frame is delivered from LinkConnection.data_received (fleetctl.frame_sink),
    # not a loop round later from the receive task; order with text frames is kept.
    reading = watch_reads(monkeypatch, LinkConnection)
    in_read: list[bool] = []
    received: list[bytes] = []

    def on_frame(frame: bytes) -> None:
        in_read.append(reading())
        received.append(frame)

    cfg = robot_config(server.url, tmp_path)
    async with Consumer.open(server.url) as operator, running(
        RobotLink(cfg, on_frame=on_frame, tuning=FAST)
    ) as link:
        await wait_until(lambda: link.stats()["subscribed"] == ["/r1/cmd.*"])
        for i in range(20):
            await operator.ws.send(string_frame("/r1/cmd", f"c{i}", no_drop=True, seq=i + 1))
        await wait_until(lambda: len(received) == 20)
        assert [decode_text(f) for f in received] == [f"c{i}" for i in range(20)]
        assert all(in_read)


async def test_duplicate_no_drop_frames_are_dropped_on_receive(
    server: RelayServer, tmp_path: Path
) -> None:
    received: list[bytes] = []
    cfg = robot_config(server.url, tmp_path)
    async with Consumer.open(server.url) as operator, running(
        RobotLink(cfg, on_frame=received.append, tuning=FAST)
    ) as link:
        await wait_until(lambda: link.stats()["subscribed"] == ["/r1/cmd.*"])
        # A resend is the same frame again (same seq and publish time).
        frames = {seq: string_frame("/r1/cmd", f"s{seq}", no_drop=True, seq=seq)
                  for seq in (1, 2, 3, 4)}
        for seq in [1, 2, 2, 3, 1, 4]:
            await operator.ws.send(frames[seq])
        await operator.ws.send(string_frame("/r1/cmd", "end", no_drop=True, seq=5))
        await wait_until(lambda: bool(received) and decode_text(received[-1]) == "end")
        assert [decode_text(f) for f in received] == ["s1", "s2", "s3", "s4", "end"]
        assert link.stats()["received"]["duplicates"] == 2


async def test_server_restart_every_no_drop_message_delivered_in_order(tmp_path: Path) -> None:
    srv = make_server(tmp_path)
    await srv.start()
    port = srv.port
    forwarder = TcpForwarder(port)
    await forwarder.accept()
    cfg = robot_config(url_of(forwarder.port), tmp_path,
                       limits={"reconnect_min_s": 0.05, "reconnect_max_s": 0.2})
    seq = 0

    def offer(link: RobotLink, n: int) -> None:
        nonlocal seq
        for _ in range(n):
            seq += 1
            link.offer("/r1/events", string_frame("/r1/events", f"e{seq}", no_drop=True,
                                                  seq=seq), priority=1.0, no_drop=True)

    try:
        async with running(RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)) as link:
            async with Consumer.open(srv.url, "/r1/events") as before:
                offer(link, 50)
                await wait_until(lambda: len(before.frames) == 50)
            await forwarder.refuse()  # the robot cannot reach the server while it restarts
            await srv.stop()
            await wait_until(lambda: not link.stats()["connected"])
            offer(link, 50)  # queued while down
            srv = make_server(tmp_path, port)
            await srv.start()
            async with Consumer.open(srv.url, "/r1/events") as after:
                await forwarder.accept()
                await wait_until(lambda: link.stats()["reconnects"] >= 1)
                offer(link, 50)
                await wait_until(lambda: "e150" in after.texts())
                got = [int(t[1:]) for t in after.texts()]
        assert [s for s in got if s > 50] == list(range(51, 151))
        assert link.stats()["no_drop_overflow"] == 0
    finally:
        await forwarder.refuse()
        await srv.stop()


async def test_clean_server_close_is_reported_and_reconnected(tmp_path: Path) -> None:
    srv = make_server(tmp_path)
    await srv.start()
    port = srv.port
    cfg = robot_config(url_of(port), tmp_path,
                       limits={"reconnect_min_s": 0.05, "reconnect_max_s": 0.1})
    try:
        async with running(RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)) as link:
            await wait_until(lambda: bool(link.stats()["identities"]))
            await srv.stop()  # closes every connection with 1001
            await wait_until(lambda: not link.stats()["connected"])
            assert str(link.stats()["last_close"]).startswith("1001")
            srv = make_server(tmp_path, port)
            await srv.start()
            await wait_until(lambda: link.stats()["reconnects"] == 1
                             and link.stats()["subscribed"] == ["/r1/cmd.*"])
    finally:
        await srv.stop()


async def test_silent_link_is_detected_and_no_drop_survives(
    server: RelayServer, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    forwarder = TcpForwarder(server.port)
    await forwarder.accept()
    cfg = robot_config(url_of(forwarder.port), tmp_path,
                       limits={"reconnect_min_s": 0.05, "reconnect_max_s": 0.2})
    caplog.set_level(logging.WARNING, "fleetctl.client.link")
    try:
        async with Consumer.open(server.url, "/r1/events") as consumer, running(
            RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
        ) as link:
            await wait_until(lambda: link.stats()["connected"])
            forwarder.stall()
            for i in range(1, 21):
                link.offer("/r1/events", string_frame("/r1/events", f"e{i}", no_drop=True,
                                                      seq=i), priority=1.0, no_drop=True)
            await wait_until(lambda: link.stats()["link_timeouts"] >= 1)
            await wait_until(lambda: "e20" in consumer.texts())
            got = [int(t[1:]) for t in consumer.texts()]
        assert got == list(range(1, 21))
        assert any("no pong" in r.getMessage() for r in caplog.records)
    finally:
        await forwarder.refuse()


async def test_commands_sent_while_the_robot_is_away_arrive_once_in_order(
    server: RelayServer, tmp_path: Path
) -> None:
    """The robot's session: commands sent into a silent link or while it reconnects are
    kept by the server and delivered after the reconnect, in order, each once."""
    forwarder = TcpForwarder(server.port)
    await forwarder.accept()
    cfg = robot_config(url_of(forwarder.port), tmp_path,
                       limits={"reconnect_min_s": 0.05, "reconnect_max_s": 0.2})
    received: list[bytes] = []

    async def command(operator: Consumer, first: int, n: int) -> None:
        for seq in range(first, first + n):
            await operator.ws.send(string_frame("/r1/cmd", f"c{seq}", no_drop=True, seq=seq))

    try:
        async with Consumer.open(server.url) as operator, running(
            RobotLink(cfg, on_frame=received.append, tuning=FAST)
        ) as link:
            await wait_until(lambda: link.stats()["subscribed"] == ["/r1/cmd.*"])
            await command(operator, 1, 20)
            await wait_until(lambda: len(received) == 20)
            forwarder.stall()  # the radio goes silent: bytes written now go nowhere
            await command(operator, 21, 80)
            await wait_until(lambda: link.stats()["reconnects"] >= 1)
            await command(operator, 101, 20)
            await wait_until(lambda: len(received) >= 120)
            assert [decode_text(f) for f in received] == [f"c{i}" for i in range(1, 121)]
            assert link.stats()["session_resumes"] >= 1
        # stop() unsubscribed everything: that ended the session on the server.
        assert len(server.core.sessions) == 0
    finally:
        await forwarder.refuse()


async def test_reinstated_subscriptions_not_in_the_config_are_dropped(
    server: RelayServer, tmp_path: Path
) -> None:
    from websockets.asyncio.client import connect

    from fleetctl.wire.control import encode_subscription

    headers = {"Authorization": f"Bearer {ROBOT_TOKEN}", "X-Fleetctl-Session": "r1"}
    async with connect(server.url, additional_headers=headers) as old_run:
        for pattern in ("/r1/cmd.*", "/r1/cmd_old"):
            await old_run.send(encode_subscription(pattern))
        await wait_until(lambda: len(next(iter(server.core.sessions)).patterns) == 2)
    cfg = robot_config(server.url, tmp_path)
    async with running(RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)):
        await wait_until(lambda: list(next(iter(server.core.sessions)).patterns)
                         == ["/r1/cmd.*"])


async def test_clean_link_window_is_not_one_message_per_rtt(
    server: RelayServer, tmp_path: Path
) -> None:
    cfg = robot_config(server.url, tmp_path)
    frame = string_frame("/r1/events", "z" * 60_000, no_drop=True, seq=1)
    async with Consumer.open(server.url, "/r1/events") as consumer, running(
        RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
    ) as link:
        await wait_until(lambda: link.stats()["connected"])
        max_in_flight = 0

        def done() -> bool:
            nonlocal max_in_flight
            max_in_flight = max(max_in_flight, link.scheduler.in_flight_frames)
            return len(consumer.frames) == 200

        for _ in range(200):
            link.offer("/r1/events", frame, priority=1.0, no_drop=True)
        await wait_until(done)
        assert max_in_flight > 1


async def test_bad_token_is_reported_and_retried(server: RelayServer, tmp_path: Path,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    (tmp_path / "bad.token").write_text("wrong-token")
    cfg = robot_config(server.url, tmp_path, limits={"reconnect_min_s": 0.05,
                                                     "reconnect_max_s": 0.1})
    cfg = type(cfg)(**{**cfg.__dict__, "token": "wrong-token"})
    caplog.set_level(logging.INFO, "fleetctl.client.link")
    async with running(RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)) as link:
        await wait_until(lambda: link.stats()["connects"] >= 5)
        assert str(link.stats()["last_close"]).startswith("4401")
    assert "wrong-token" not in caplog.text
    # Explained once, with what to check (each attempt logged three lines: "server error
    # bad_token on None" and the 4401 close twice).
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING
              and r.name.startswith("fleetctl.client")]
    assert len(errors) == 1, errors
    assert errors[0].startswith(f"connection to {server.url} closed: 4401 bad token: the server "
                                "knows no such token: check token_file")
    assert "on None" not in caplog.text
    # Each of the >= 5 retries' connects was an INFO line too (every 5 s for as long as
    # the token was wrong); after the first they are DEBUG until a welcome.
    connected = [r for r in caplog.records if r.getMessage().startswith("connected to")]
    assert len(connected) == 1


async def test_ip_identity_with_bind_address(server: RelayServer, tmp_path: Path) -> None:
    from fleetctl.client.config import parse_client_config

    cfg = parse_client_config({
        "server_url": server.url, "robot_name": "r2", "bind_address": "127.0.0.2",
        "publish": [{"topic": "/scan", "type": "std_msgs/msg/String"}]})
    async with Consumer.open(server.url, "/r2/.*") as consumer, running(
        RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
    ) as link:
        await wait_until(lambda: link.stats()["identities"] == ["r2"])
        link.offer("/r2/scan", string_frame("/r2/scan", "hello"), priority=1, no_drop=False)
        await wait_until(lambda: consumer.texts() == ["hello"])


async def test_offer_threadsafe_and_admit_from_another_thread(
    server: RelayServer, tmp_path: Path
) -> None:
    cfg = robot_config(server.url, tmp_path, publish=[
        {"topic": "/chatter", "type": "std_msgs/msg/String", "rate_limit_hz": 5.0}])
    async with Consumer.open(server.url, "/r1/chatter") as consumer, running(
        RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
    ) as link:
        frame = string_frame("/r1/chatter", "t")

        def publish_from_thread() -> list[bool]:
            admitted = [link.admit("/r1/chatter") for _ in range(3)]
            link.offer_threadsafe("/r1/chatter", frame, priority=1.0, no_drop=False)
            return admitted

        admitted = await asyncio.to_thread(publish_from_thread)
        assert admitted == [True, False, False]
        await wait_until(lambda: consumer.texts() == ["t"])
        assert link.stats()["topics"]["/r1/chatter"]["rate_limited"] == 2


async def test_offer_threadsafe_on_the_loop_thread_queues_at_once(tmp_path: Path) -> None:
    # The loop-thread intake (fleetctl.client.ros.intake) calls it there: a hop through
    # call_soon_threadsafe would write the loop's self-pipe and wake it for nothing.
    cfg = robot_config("ws://127.0.0.1:9/", tmp_path)
    link = RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
    link.offer_threadsafe("/r1/chatter", string_frame("/r1/chatter"), priority=1.0,
                          no_drop=False)
    assert link.scheduler.has_sendable()  # no await in between: queued synchronously


async def test_invalid_frame_is_dropped_and_link_survives(
    server: RelayServer, tmp_path: Path
) -> None:
    cfg = robot_config(server.url, tmp_path, limits={"max_fragment_bytes": 1024})
    async with Consumer.open(server.url, "/r1/.*") as consumer, running(
        RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
    ) as link:
        link.offer("/r1/junk", b"\x00" * 5000, priority=1.0, no_drop=False)  # unsplittable
        link.offer("/r1/chatter", string_frame("/r1/chatter", "ok"), priority=1.0,
                   no_drop=False)
        await wait_until(lambda: consumer.texts() == ["ok"])
        stats = link.stats()
        assert stats["topics"]["/r1/junk"]["dropped_invalid"] == 1
        assert "/r1/junk" in stats["last_error"]


async def test_baseline_fixed_window_still_delivers(server: RelayServer, tmp_path: Path) -> None:
    cfg = robot_config(server.url, tmp_path)
    baseline = SchedulerConfig(fixed_window_messages=1, fragments=False)
    async with Consumer.open(server.url, "/r1/events") as consumer, running(
        RobotLink(cfg, on_frame=lambda f: None, tuning=FAST, scheduler_config=baseline)
    ) as link:
        for i in range(30):
            link.offer("/r1/events", string_frame("/r1/events", f"e{i}", no_drop=True, seq=i),
                       priority=1.0, no_drop=True)
        await wait_until(lambda: len(consumer.frames) == 30)
        assert link.scheduler.in_flight_frames <= 1


async def test_stop_does_not_wait_for_a_hanging_connection_attempt(tmp_path: Path) -> None:
    accepted = asyncio.Event()
    writers: list[asyncio.StreamWriter] = []

    async def silent(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writers.append(writer)  # accept TCP, never answer the upgrade
        accepted.set()

    hang = await asyncio.start_server(silent, "127.0.0.1", 0)
    port = hang.sockets[0].getsockname()[1]
    cfg = robot_config(url_of(port), tmp_path)
    link = RobotLink(cfg, on_frame=lambda f: None, tuning=LinkTuning(open_timeout_s=30.0))
    task = asyncio.create_task(link.run())
    try:
        await asyncio.wait_for(accepted.wait(), 5.0)
        await asyncio.wait_for(link.stop(), 2.0)
        await asyncio.wait_for(task, 2.0)
    finally:
        for writer in writers:
            writer.transport.abort()
        hang.close()
        await hang.wait_closed()


def test_backoff_is_exponential_capped_and_jittered() -> None:
    import random

    rng = random.Random(1)
    delays = [backoff_delay_s(n, 0.1, 5.0, rng) for n in range(12)]
    assert all(0.05 <= d <= 0.1 for d in delays[:1])
    assert all(2.5 <= d <= 5.0 for d in delays[8:])
    assert len({round(d, 6) for d in delays}) == len(delays)  # jittered



def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


async def test_bind_address_on_no_interface_is_explained_once_then_reminded(
    server: RelayServer, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # 192.0.2.0/24 (TEST-NET-1) is on no interface here: bind() fails with EADDRNOTAVAIL,
    # as the robot's WireGuard address does while its tunnel is down.
    link, clock = _reminding_link(server.url, tmp_path, caplog, bind_address="192.0.2.7")
    cfg = link.config
    async with running(link):
        await wait_until(lambda: link.stats()["connect_failures"] >= 20)
        warnings = _warnings(caplog)
        assert len(warnings) == 1, warnings
        assert "cannot bind 192.0.2.7 (bind_address" in warnings[0]
        assert "the WireGuard tunnel is down?" in warnings[0]
        assert "wg show" in warnings[0] and "wg-quick@fleet0" in warnings[0]
        assert not any("cannot connect to" in m for m in warnings)

        warnings = await _thirty_one_seconds_on(link, clock, caplog)
        assert warnings[1].startswith("still cannot bind 192.0.2.7: the tunnel has been down "
                                      "for 31 s")

        # The tunnel comes back: the address is usable again and the link connects.
        link.config = type(cfg)(**{**cfg.__dict__, "bind_address": "127.0.0.1"})
        await wait_until(lambda: link.stats()["connected"])
    assert any(r.levelno == logging.INFO and "on an interface again after 31 s" in r.getMessage()
               for r in caplog.records)


async def test_a_new_outage_is_explained_again(tmp_path: Path,
                                               caplog: pytest.LogCaptureFixture) -> None:
    cfg = robot_config("ws://127.0.0.1:9/", tmp_path, bind_address="192.0.2.7",
                       limits={"reconnect_min_s": 0.01, "reconnect_max_s": 0.02})
    caplog.set_level(logging.WARNING, "fleetctl.client.link")
    link = RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
    async with running(link):
        await wait_until(lambda: link.stats()["connect_failures"] >= 3)
        # Bound again, but nothing listens on port 9: an ordinary failure ends the outage.
        link.config = type(cfg)(**{**cfg.__dict__, "bind_address": "127.0.0.1"})
        await wait_until(lambda: any("cannot connect to" in m for m in _warnings(caplog)))
        link.config = cfg
        await wait_until(lambda: sum("cannot bind" in m for m in _warnings(caplog)) == 2)


def _reminding_link(url: str, tmp_path: Path, caplog: pytest.LogCaptureFixture,
                    **config: Any) -> tuple[RobotLink, ManualClock]:
    """A link to *url* on a manual clock that retries every 0.01-0.02 s and reminds every
    30 s of an outage, its log captured from DEBUG; *config* goes to robot_config."""
    cfg = robot_config(url, tmp_path, limits={"reconnect_min_s": 0.01, "reconnect_max_s": 0.02},
                       **config)
    clock = ManualClock(1_000.0)
    caplog.set_level(logging.DEBUG, "fleetctl.client.link")
    link = RobotLink(cfg, on_frame=lambda f: None, clock=clock,
                     tuning=LinkTuning(bind_reminder_interval_s=30.0, open_timeout_s=1.0))
    return link, clock


async def _thirty_one_seconds_on(link: RobotLink, clock: ManualClock,
                                 caplog: pytest.LogCaptureFixture) -> list[str]:
    """Move *clock* 29 s into an outage (no reminder yet), then 2 s more (one reminder),
    waiting for five more failed attempts after each; returns the warnings logged."""
    clock.now_s += 29.0
    failures = link.stats()["connect_failures"]
    await wait_until(lambda: link.stats()["connect_failures"] >= failures + 5)
    assert len(_warnings(caplog)) == 1
    clock.now_s += 2.0
    failures = link.stats()["connect_failures"]
    await wait_until(lambda: link.stats()["connect_failures"] >= failures + 5)
    warnings = _warnings(caplog)
    assert len(warnings) == 2, warnings
    return warnings


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def test_a_server_down_at_start_is_explained_once_then_reminded(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A robot started before its server: one WARNING saying the link keeps trying, a
    # reminder every 30 s, the attempts in between at DEBUG (it was a WARNING per attempt,
    # every 5 s, for as long as the server was down), and one INFO when it is reached.
    port = _free_port()
    link, clock = _reminding_link(url_of(port), tmp_path, caplog)
    async with running(link):
        await wait_until(lambda: link.stats()["connect_failures"] >= 20)
        warnings = _warnings(caplog)
        assert len(warnings) == 1, warnings
        assert warnings[0].startswith(f"cannot connect to {url_of(port)}: ")
        assert "retrying every 0.02 s or less, quietly (a reminder every 30 s)" in warnings[0]

        warnings = await _thirty_one_seconds_on(link, clock, caplog)
        assert warnings[1].startswith(f"still cannot connect to {url_of(port)} after 31 s (")

        async with make_server(tmp_path, port):
            await wait_until(lambda: link.stats()["connected"])
            assert any(r.levelno == logging.INFO
                       and r.getMessage().startswith(f"reached {url_of(port)} after 31 s (")
                       for r in caplog.records)
            assert len(_warnings(caplog)) == 2


async def test_two_clients_of_one_robot_say_so_and_back_off(
    server: RelayServer, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # The same client.yaml run twice (the service and a run by hand): each connection took
    # the session from the other at once, 37 times in 6 s, each close a WARNING "4409".
    cfg = robot_config(server.url, tmp_path)
    tuning = LinkTuning(keepalive_interval_s=0.1, link_timeout_s=0.6, open_timeout_s=1.0,
                        takeover_backoff_s=0.5)
    caplog.set_level(logging.ERROR, "fleetctl.client.link")
    first, second = (RobotLink(cfg, on_frame=lambda f: None, tuning=tuning) for _ in range(2))

    def errors() -> list[str]:
        return [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]

    async with running(first):
        await wait_until(lambda: first.stats()["connected"])
        async with running(second):
            await wait_until(lambda: any("(3 time(s) in a row)" in m for m in errors()))
            # Waits of 0.4-0.5, 0.8-1 and 1.6-2 s between takeovers: a handful of
            # connections in all, not one every 0.1 s.
            assert first.stats()["connects"] + second.stats()["connects"] <= 8
    said = errors()[0]
    assert said.startswith(f"another client connected to {server.url} as robot r1 and took "
                           "this session over (1 time(s) in a row): is a second fleetctl "
                           "client running with this robot_name")


async def test_held_offers_are_written_in_the_callers_turn(
    server: RelayServer, tmp_path: Path
) -> None:
    # What the loop-thread intake does around a take: hold, offer, send_held. When the
    # send loop is idle the frame is on the connection before send_held returns (no loop
    # round in between); every frame arrives once, in order, either way.
    cfg = robot_config(server.url, tmp_path)
    topic = "/r1/events"
    async with Consumer.open(server.url, "/r1/.*") as consumer, running(
        RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)
    ) as link:
        link.hold_wakes()  # before any connection: send_held can only wake the loop
        link.offer(topic, string_frame(topic, "e0", no_drop=True, seq=1), priority=1.0,
                   no_drop=True)
        link.send_held()
        offered = 1

        def sent() -> int:
            topics = link.stats()["topics"]
            return int(topics[topic]["sent_frames"]) if topic in topics else 0

        def offer_held_and_check() -> bool:
            nonlocal offered
            before = sent()
            link.hold_wakes()
            link.offer(topic, string_frame(topic, f"e{offered}", no_drop=True,
                                           seq=offered + 1), priority=1.0, no_drop=True)
            offered += 1
            link.send_held()
            return sent() == before + 1  # written synchronously

        await wait_until(offer_held_and_check)
        await wait_until(lambda: len(consumer.frames) >= offered)
        assert consumer.texts(topic) == [f"e{i}" for i in range(offered)]
        await wait_until(lambda: link.stats()["in_flight_bytes"] == 0)
        assert link.stats()["topics"][topic]["acked"] == offered


async def test_a_token_file_with_a_byte_order_mark_authenticates(
    server: RelayServer, tmp_path: Path
) -> None:
    """A token file saved by a Windows editor (UTF-8 with BOM, CRLF): the BOM went out as
    part of the token and the relay answered 4401 'bad token' for ever."""
    from fleetctl.client.config import load_client_config
    from tests.client.conftest import ROBOT_TOKEN

    (tmp_path / "r1.token").write_bytes(b"\xef\xbb\xbf" + ROBOT_TOKEN.encode() + b"\r\n")
    (tmp_path / "client.yaml").write_text(
        f"server_url: {server.url}\nrobot_name: r1\ntoken_file: r1.token\n")
    cfg = load_client_config(tmp_path / "client.yaml")
    async with running(RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)) as link:
        await wait_until(lambda: link.stats()["identities"] == ["r1"])


async def test_a_port_that_accepts_and_never_answers_is_said_in_words(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A listener that accepts TCP and never answers the upgrade (a stalled relay, another
    service): the log said only 'cannot connect to URL: TimeoutError'."""
    held: list[asyncio.StreamWriter] = []

    async def hold(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        held.append(writer)

    silent = await asyncio.start_server(hold, "127.0.0.1", 0)
    port = silent.sockets[0].getsockname()[1]
    caplog.set_level(logging.WARNING, "fleetctl.client.link")
    cfg = robot_config(url_of(port), tmp_path, limits={"standby_connection": False})
    try:
        async with running(RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)):
            await wait_until(lambda: any("cannot connect" in r.getMessage()
                                         for r in caplog.records))
    finally:
        silent.close()
        for writer in held:
            writer.transport.abort()
    said = next(r.getMessage() for r in caplog.records if "cannot connect" in r.getMessage())
    assert said.startswith(f"cannot connect to {url_of(port)}: the connection was accepted but "
                           "the WebSocket handshake got no answer in 1 s (a stalled relay, or "
                           "something else listens on that port); retrying")


async def test_a_robot_clock_an_hour_behind_its_server_is_said_once(
    server: RelayServer, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A robot without NTP: every page showed its live data as an hour old, and nothing on
    the robot said why. The relay's upgrade answer carries its Date."""
    import time

    caplog.set_level(logging.INFO, "fleetctl.client.link")
    cfg = robot_config(server.url, tmp_path)
    behind = RobotLink(cfg, on_frame=lambda f: None, tuning=FAST,
                       wall_clock_ns=lambda: time.time_ns() - 3600 * 10**9)
    async with running(behind) as link:
        await wait_until(lambda: link.stats()["identities"] == ["r1"])
    said = [r.getMessage() for r in caplog.records if "wall clock" in r.getMessage()]
    assert len(said) == 1, said
    assert said[0].startswith("this robot's wall clock is about 3600 s behind "
                              f"{server.url}'s") or "about 3599 s" in said[0]  # Date's rtt
    caplog.clear()
    async with running(RobotLink(cfg, on_frame=lambda f: None, tuning=FAST)) as link:
        await wait_until(lambda: link.stats()["identities"] == ["r1"])
    assert "wall clock" not in caplog.text  # in step: nothing to say
