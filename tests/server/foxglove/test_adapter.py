"""The Foxglove protocol end to end: a spec-written client against a real relay, robots
sending real frames, CDR checked with rosbags' own deserializer."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import AsyncIterator, Callable
from typing import Any

import numpy as np
import pytest

from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerLimits, WebConfig
from fleetctl.server.foxglove.adapter import CHANNEL_LINGER_S
from fleetctl.wire.codec import default_codec
from tests.server.conftest import ALICE_TOKEN, BOB_TOKEN, client, wait_for
from tests.server.foxglove.conftest import POSE_TYPE, REFERENCE, SCAN_TYPE, scan, scan_frame
from tests.server.foxglove.fxclient import Viewer, https_get, open_viewer, ticket


async def test_viewer_gets_channels_and_cdr_that_rosbags_decodes(
        fx_server: RelayServer) -> None:
    async with client(fx_server, source="127.0.0.2") as robot:
        await robot.send(scan_frame("/husky1/scan", 0))
        await wait_for(lambda: bool(fx_server.foxglove.catalog.channels()))
        async with open_viewer(fx_server.web_port, await ticket(fx_server.web_port,
                                                                ALICE_TOKEN)) as ws:
            viewer = Viewer(ws)
            await viewer.until(lambda: viewer.channel("/husky1/scan") is not None)
            assert viewer.server_info is not None and viewer.ops[0] == "serverInfo"
            assert viewer.server_info["capabilities"] == ["clientPublish"]
            assert viewer.server_info["supportedEncodings"] == ["cdr"]
            channel = viewer.channel("/husky1/scan")
            assert channel is not None
            assert (channel["encoding"], channel["schemaEncoding"], channel["schemaName"]) == (
                "cdr", "ros2msg", SCAN_TYPE)
            assert channel["schema"].startswith("std_msgs/Header header")
            await viewer.subscribe(7, channel["id"])
            await wait_for(lambda: bool(fx_server.core.subs.receivers("/husky1/scan")))
            for seq in (1, 2, 3):
                await robot.send(scan_frame("/husky1/scan", seq))
                await viewer.until(lambda n=seq: len(viewer.messages) >= n)
            for seq, (sub_id, stamp, payload) in zip((1, 2, 3), viewer.messages, strict=True):
                assert sub_id == 7 and stamp > 0
                got = REFERENCE.deserialize_cdr(payload, SCAN_TYPE)
                sent = scan(seq)
                assert got.header.stamp.sec == seq and got.header.frame_id == "laser"
                np.testing.assert_array_equal(got.ranges, sent.ranges)
                assert got.range_max == sent.range_max


async def test_transcoded_once_per_frame_for_many_viewers(fx_server: RelayServer) -> None:
    port = fx_server.web_port
    async with client(fx_server, source="127.0.0.2") as robot:
        await robot.send(scan_frame("/husky1/scan", 0))
        await wait_for(lambda: bool(fx_server.foxglove.catalog.channels()))
        tickets = [await ticket(port, ALICE_TOKEN) for _ in range(3)]
        async with open_viewer(port, tickets[0]) as a, open_viewer(port, tickets[1]) as b, \
                open_viewer(port, tickets[2]) as c:
            viewers = [Viewer(ws) for ws in (a, b, c)]
            for viewer in viewers:
                await viewer.until(lambda v=viewer: v.channel("/husky1/scan") is not None)
                channel = viewer.channel("/husky1/scan")
                assert channel is not None
                await viewer.subscribe(1, channel["id"])
            await wait_for(lambda: len(fx_server.core.subs.receivers("/husky1/scan")) == 3)
            before = fx_server.foxglove.transcoder.transcoded
            await robot.send(scan_frame("/husky1/scan", 1))
            for viewer in viewers:
                await viewer.until(lambda v=viewer: len(v.messages) == 1)
            assert fx_server.foxglove.transcoder.transcoded - before == 1
            status, body = await https_get(fx_server.port, "/metrics", secure=False)
            text = body.decode()
            assert status == 200 and 'fleetctl_foxglove_tickets_total{result="issued"} 3' in text
            assert "fleetctl_foxglove_viewers 3" in text
            assert 'fleetctl_foxglove_transcoded_total{result="hit"} 2' in text


@contextlib.asynccontextmanager
async def bob_sees_husky1_of_two(
        fx_server: RelayServer) -> AsyncIterator[tuple[Any, Any, Viewer]]:
    """husky1 and husky2 each send a scan; bob (receives /husky1/.* only) is offered
    husky1's channel and not husky2's. Yields the two robots' connections and bob."""
    port = fx_server.web_port
    async with client(fx_server, source="127.0.0.2") as husky1, \
            client(fx_server, source="127.0.0.3") as husky2:
        await husky1.send(scan_frame("/husky1/scan", 0))
        await husky2.send(scan_frame("/husky2/scan", 0))
        await wait_for(lambda: len(fx_server.foxglove.catalog.channels()) == 2)
        async with open_viewer(port, await ticket(port, BOB_TOKEN)) as ws:
            viewer = Viewer(ws)
            await viewer.until(lambda: viewer.channel("/husky1/scan") is not None)
            assert viewer.channel("/husky2/scan") is None
            yield husky1, husky2, viewer


async def test_viewer_is_offered_only_what_it_may_receive(fx_server: RelayServer) -> None:
    fx_server.foxglove.catalog.linger_s = 0.2  # a gone robot's channels linger (10 s)
    async with bob_sees_husky1_of_two(fx_server) as (husky1, husky2, viewer):
        assert viewer.server_info is not None
        assert viewer.server_info["capabilities"] == []  # bob may send nothing
        # A channel it was not offered cannot be subscribed by guessing its id.
        hidden = next(c.id for c in fx_server.foxglove.catalog.channels()
                      if c.topic == "/husky2/scan")
        await viewer.subscribe(1, hidden)
        await viewer.until(lambda: bool(viewer.statuses))
        assert viewer.statuses[0]["level"] == 2
        # Topics come and go: a new one is advertised live, a gone robot unadvertised.
        await husky1.send(scan_frame("/husky1/scan2", 0))
        await viewer.until(lambda: viewer.channel("/husky1/scan2") is not None)
        await husky2.send(scan_frame("/husky2/other", 0))
        await husky1.close()
        await viewer.until(lambda: viewer.channel("/husky1/scan") is None)
        assert viewer.channel("/husky2/other") is None


def pose_cdr(x: float) -> bytes:
    t = REFERENCE.types
    msg = t[POSE_TYPE](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=1,
                                                                               nanosec=2),
                                        frame_id="map"),
        pose=t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=x, y=2.0,
                                                                               z=0.0),
                                         orientation=t["geometry_msgs/msg/Quaternion"](
                                             x=0.0, y=0.0, z=0.0, w=1.0)))
    return bytes(REFERENCE.serialize_cdr(msg, POSE_TYPE))


async def test_client_publish_reaches_the_robot_as_a_fleet_frame(
        fx_server: RelayServer) -> None:
    from tests.server.conftest import next_binary, subscribe

    port = fx_server.web_port
    async with client(fx_server, source="127.0.0.2") as robot:
        assert (await subscribe(robot, "/husky1/goal_pose"))["type"] == "subscribed"
        async with open_viewer(port, await ticket(port, ALICE_TOKEN)) as ws:
            viewer = Viewer(ws)
            await viewer.until(lambda: viewer.server_info is not None)
            await viewer.advertise(5, "/husky1/goal_pose", "geometry_msgs/PoseStamped")
            await viewer.publish(5, pose_cdr(4.5))
            meta, msg = default_codec().decode(await next_binary(robot))
            assert (meta.topic, meta.type) == ("/husky1/goal_pose", POSE_TYPE)
            assert (msg.pose.position.x, msg.header.frame_id) == (4.5, "map")


async def test_client_publish_outside_send_rules_is_refused(fx_server: RelayServer) -> None:
    port = fx_server.web_port
    async with open_viewer(port, await ticket(port, BOB_TOKEN)) as ws:
        viewer = Viewer(ws)  # bob may only receive
        await viewer.until(lambda: viewer.server_info is not None)
        before = fx_server.metrics.errors.get("unauthorized_send", 0)
        await viewer.advertise(5, "/husky1/goal_pose", "geometry_msgs/msg/PoseStamped")
        await viewer.until(lambda: bool(viewer.statuses))
        assert viewer.statuses[0]["level"] == 2
        assert "unauthorized_send" in viewer.statuses[0]["message"]
        await viewer.publish(5, pose_cdr(1.0))  # on the refused channel
        await viewer.until(lambda: len(viewer.statuses) == 2)
        assert viewer.statuses[1]["level"] == 2
        assert fx_server.metrics.errors["unauthorized_send"] == before + 1


@pytest.mark.parametrize("text", ["not json", "[1, 2]", '{"op": "fly"}',
                                  '{"op": "subscribe", "subscriptions": [{"id": -1}]}'])
async def test_bad_requests_get_an_error_status_not_a_crash(fx_server: RelayServer,
                                                            text: str) -> None:
    port = fx_server.web_port
    async with open_viewer(port, await ticket(port, ALICE_TOKEN)) as ws:
        viewer = Viewer(ws)
        await viewer.until(lambda: viewer.server_info is not None)
        await ws.send(text)
        await ws.send(b"\x07garbage")
        await viewer.until(lambda: len(viewer.statuses) == 2)
        assert [s["level"] for s in viewer.statuses] == [2, 2]
        await viewer.until(lambda: "advertise" in viewer.ops)  # still served


async def test_slow_viewer_does_not_hold_back_others(
        make_server: Callable[..., RelayServer], web_config: WebConfig) -> None:
    queue_bytes = 256 * 1024
    async with make_server(web=web_config,
                           limits=ServerLimits(outbound_queue_bytes=queue_bytes)) as srv, \
            client(srv, source="127.0.0.2") as robot:
        port = srv.web_port
        await robot.send(scan_frame("/husky1/scan", 0))
        await wait_for(lambda: bool(srv.foxglove.catalog.channels()))
        # The slow tab never reads: its client buffers one message (max_queue=1), then
        # the kernel's socket buffers fill; the relay's queue for it keeps the latest scan.
        async with open_viewer(port, await ticket(port, ALICE_TOKEN), max_queue=1) as slow_ws, \
                open_viewer(port, await ticket(port, ALICE_TOKEN)) as fast_ws:
            slow, fast = Viewer(slow_ws), Viewer(fast_ws)
            for viewer in (slow, fast):
                await viewer.until(lambda v=viewer: v.channel("/husky1/scan") is not None)
                channel = viewer.channel("/husky1/scan")
                assert channel is not None
                await viewer.subscribe(1, channel["id"])
            await wait_for(lambda: len(srv.core.subs.receivers("/husky1/scan")) == 2)
            slow_peer = srv.foxglove.viewers[min(srv.foxglove.viewers)].peer  # opened first
            floats = 100_000  # 400 KB scans
            seq = 0
            while not slow_peer.outbound.dropped_total:
                seq += 1
                assert seq <= 200, "the slow viewer's queue never dropped"
                await robot.send(scan_frame("/husky1/scan", seq, floats))
                await fast.until(lambda n=seq: len(fast.messages) >= n, timeout_s=10)
            assert srv.metrics.drops.get("/husky1/scan", 0) > 0
            # Bound: its byte bound, or one frame when the queue was empty.
            assert slow_peer.outbound.queued_bytes <= queue_bytes + 2 * floats * 4
            last = REFERENCE.deserialize_cdr(fast.messages[-1][2], SCAN_TYPE)
            assert last.header.stamp.sec == seq
            slow_ws.transport.abort()  # the tab is killed: no close handshake to wait for


async def test_ticket_never_reaches_a_log(fx_server: RelayServer,
                                          caplog: pytest.LogCaptureFixture) -> None:
    port = fx_server.web_port
    caplog.set_level(logging.DEBUG)
    value = await ticket(port, ALICE_TOKEN)
    async with open_viewer(port, value) as ws:
        viewer = Viewer(ws)
        await viewer.until(lambda: viewer.server_info is not None)
    # A malformed request line quoting the ticket is logged without it (HTTP/2.0 in a
    # request line: websockets refuses it, quoting the line; HTTP/1.0 is answered).
    reader, writer = await asyncio.open_connection("127.0.0.1", fx_server.port)
    writer.write(f"GET /?ticket={value} HTTP/2.0\r\n\r\n".encode())
    await asyncio.wait_for(reader.read(), 5)
    writer.close()
    await wait_for(lambda: "opening handshake failed" in caplog.text)
    # The server's records (the test's own client logs its request line at DEBUG).
    server = "\n".join(r.getMessage() for r in caplog.records
                       if r.name.startswith("fleetctl"))
    assert "ticket=<redacted>" in server and "Foxglove ticket issued to alice" in server
    assert value not in server and ALICE_TOKEN not in server


async def test_fragmented_messages_reach_the_viewer_whole(fx_server: RelayServer) -> None:
    from fleetctl.wire import fragments

    def parts(seq: int) -> list[bytes]:
        return fragments.split(scan_frame("/husky1/scan", seq, 20_000), topic="/husky1/scan",
                               message_id=seq, max_fragment_bytes=16_384, no_drop=False)

    port = fx_server.web_port
    async with client(fx_server, source="127.0.0.2") as robot:
        for part in parts(1):
            await robot.send(part)
        await wait_for(lambda: bool(fx_server.foxglove.catalog.channels()))
        async with open_viewer(port, await ticket(port, ALICE_TOKEN)) as ws:
            viewer = Viewer(ws)
            await viewer.until(lambda: viewer.channel("/husky1/scan") is not None)
            channel = viewer.channel("/husky1/scan")
            assert channel is not None and channel["schemaName"] == SCAN_TYPE
            await viewer.subscribe(3, channel["id"])
            await wait_for(lambda: bool(fx_server.core.subs.receivers("/husky1/scan")))
            for part in parts(2):
                await robot.send(part)
            await viewer.until(lambda: len(viewer.messages) == 1)
            got = REFERENCE.deserialize_cdr(viewer.messages[0][2], SCAN_TYPE)
            np.testing.assert_array_equal(got.ranges, scan(2, 20_000).ranges)


async def test_too_many_bad_messages_close_with_status_not_fleet_frames(
        fx_server: RelayServer) -> None:
    from websockets.exceptions import ConnectionClosed

    port = fx_server.web_port
    async with open_viewer(port, await ticket(port, ALICE_TOKEN)) as ws:
        viewer = Viewer(ws)  # Viewer.take requires an "op" in every text
        await viewer.until(lambda: viewer.server_info is not None)
        for _ in range(fx_server.config.limits.max_malformed_in_row):
            await ws.send("{")
        with pytest.raises(ConnectionClosed) as closed:
            await viewer.until(lambda: False)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1007
        assert viewer.statuses and all(s["level"] == 2 for s in viewer.statuses)


async def test_auth_reload_rechooses_the_channels(fx_server: RelayServer) -> None:
    from tests.server.conftest import AUTH, auth_map

    async with bob_sees_husky1_of_two(fx_server) as (_, _, viewer):
        raw = {**AUTH, "identities": [
            {**i, "rules": [{"topic": "/husky2/.*", "op": "receive"}]}
            if i["name"] == "bob" else i for i in AUTH["identities"]]}
        fx_server.core.reload_auth(auth_map(raw))
        await viewer.until(lambda: viewer.channel("/husky2/scan") is not None)
        assert viewer.channel("/husky1/scan") is None


async def test_each_item_of_a_request_is_a_control_request(fx_server: RelayServer) -> None:
    # A request carries up to 1024 items: 600 requests of refused channels and client
    # channels held the event loop for 13 s (other clients' frames 1.4 s late).
    port = fx_server.web_port
    async with open_viewer(port, await ticket(port, ALICE_TOKEN)) as ws:
        viewer = Viewer(ws)
        await viewer.until(lambda: viewer.server_info is not None)
        channels = [{"id": i, "topic": f"/husky1/x{i}", "encoding": "cdr",
                     "schemaName": "std_msgs/msg/String"} for i in range(1024)]
        await ws.send(json.dumps({"op": "advertise", "channels": channels}))
        await viewer.until(lambda: any("rate_limited" in s["message"]
                                       for s in viewer.statuses))
        limits = fx_server.config.limits
        burst = max(limits.max_subscriptions_per_connection, 64)
        # The burst's channels were taken silently, the rest refused with one status.
        assert len(viewer.statuses) == 1 and burst < len(channels)
        assert fx_server.metrics.errors["rate_limited"] == 1


async def test_a_robot_reconnecting_keeps_its_channels_and_the_viewers_subscriptions(
        fx_server: RelayServer) -> None:
    """A channel went with its last sender's connection: a robot that took over its
    standby or reconnected (every few minutes on a busy host) had every channel of its
    unadvertised and advertised again, which ended every viewer's subscriptions to them;
    a script viewer then got nothing more from that robot."""
    async with open_viewer(fx_server.web_port, await ticket(fx_server.web_port,
                                                            ALICE_TOKEN)) as ws:
        viewer = Viewer(ws)
        await viewer.until(lambda: viewer.server_info is not None)
        alone = len(fx_server.core.peers)
        async with client(fx_server, source="127.0.0.2") as robot:
            await robot.send(scan_frame("/husky1/scan", 1))
            await viewer.until(lambda: viewer.channel("/husky1/scan") is not None)
            channel = viewer.channel("/husky1/scan")
            assert channel is not None
            await viewer.subscribe(7, channel["id"])
            await wait_for(lambda: bool(fx_server.core.subs.receivers("/husky1/scan")))
        await wait_for(lambda: len(fx_server.core.peers) == alone)  # the server saw it go
        async with client(fx_server, source="127.0.0.2") as robot:
            await robot.send(scan_frame("/husky1/scan", 2))
            await viewer.until(lambda: len(viewer.messages) == 1)
        sub_id, _stamp, payload = viewer.messages[0]
        assert sub_id == 7 and REFERENCE.deserialize_cdr(payload, SCAN_TYPE).header.stamp.sec == 2
        assert "unadvertise" not in viewer.ops
        assert [c["id"] for c in viewer.channels.values()] == [channel["id"]]


async def test_a_channel_nobody_sends_again_goes_after_the_linger(
        fx_server: RelayServer) -> None:
    assert fx_server.foxglove.catalog.linger_s == CHANNEL_LINGER_S
    fx_server.foxglove.catalog.linger_s = 0.2
    async with open_viewer(fx_server.web_port, await ticket(fx_server.web_port,
                                                            ALICE_TOKEN)) as ws:
        viewer = Viewer(ws)
        async with client(fx_server, source="127.0.0.2") as robot:
            await robot.send(scan_frame("/husky1/scan", 1))
            await viewer.until(lambda: viewer.channel("/husky1/scan") is not None)
        await viewer.until(lambda: "unadvertise" in viewer.ops)
        assert viewer.channels == {} and fx_server.foxglove.catalog.channels() == []
