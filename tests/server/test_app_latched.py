"""Latched topics and keyframe requests through the real relay and real websockets
connections (127.0.0.1:0)."""

from __future__ import annotations

import copy
from collections.abc import AsyncIterator, Callable
from typing import Any

import numpy as np
import pytest

from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerLimits
from fleetctl.server.latched import MAX_ENTRIES
from fleetctl.wire.codec import default_codec
from fleetctl.wire.control import (
    KEYFRAME_REQUESTS_TOPIC,
    decode_keyframe_request,
    encode_keyframe_request,
)
from fleetctl.wire.fragmenter import fast_split
from fleetctl.wire.fragments import Reassembler
from fleetctl.wire.metadata import read_metadata
from fleetctl.wire.samples import header
from tests.server.conftest import (
    ALICE_TOKEN,
    AUTH,
    BOB_TOKEN,
    auth_map,
    client,
    next_binary,
    next_json,
    sha,
    subscribe,
    wait_for,
)
from tests.server.test_app import http_get
from tests.support import decode_text, string_frame

CAROL_TOKEN = "carol-secret-token"  # may receive /husky1/scan only


def _auth() -> Any:
    raw = copy.deepcopy(AUTH)
    identities: list[dict[str, Any]] = raw["identities"]  # type: ignore[assignment]
    identities.append({"name": "carol", "token_sha256": sha(CAROL_TOKEN),
                              "rules": [{"topic": "/husky1/scan", "op": "receive"}]})
    return auth_map(raw)


@pytest.fixture
async def relay(make_server: Callable[..., RelayServer]) -> AsyncIterator[RelayServer]:
    async with make_server(auth=_auth()) as srv:
        yield srv


def latched(topic: str, text: str) -> bytes:
    codec = default_codec()
    cls = codec.registry.get("std_msgs/msg/String").cls
    return codec.encode(cls(text), "std_msgs/msg/String", topic, seq=1, latched=True)


def video(topic: str) -> bytes:
    codec = default_codec()
    name = "foxglove_msgs/msg/CompressedVideo"
    stamp = header(codec.registry, "cam").stamp
    msg = codec.registry.get(name).cls(stamp, "cam", np.zeros(64, dtype=np.uint8), "h264")
    return codec.encode(msg, name, topic, seq=1)


async def test_a_viewer_connecting_later_gets_latched_messages_first(
        relay: RelayServer) -> None:
    the_map = latched("/husky1/map", "occupancy " * 3000)
    map_parts = fast_split(the_map, topic="/husky1/map", message_id=1,
                           max_fragment_bytes=4096, no_drop=False)
    description = latched("/husky1/robot_description", "<robot/>")
    async with client(relay, source="127.0.0.2") as robot:
        for part in [*map_parts, description]:
            await robot.send(part)
        await wait_for(lambda: len(relay.core.latched) == 2)
    # The robot is gone; it comes back and streams a live topic while the viewer joins.
    async with client(relay, source="127.0.0.2") as robot, \
            client(relay, token=ALICE_TOKEN) as viewer:
        await next_json(robot, "welcome")
        await robot.send(string_frame("/husky1/scan", "live 1"))
        assert (await subscribe(viewer, "/husky1/.*"))["type"] == "subscribed"
        await robot.send(string_frame("/husky1/scan", "live 2"))
        got = [await next_binary(viewer) for _ in range(len(map_parts) + 2)]
        reassembler = Reassembler(1 << 24, 10.0)
        wholes = [w for w in (reassembler.feed(f, 0.0) for f in got) if w is not None]
        assert wholes[:2] == [the_map, description]  # before any live frame
        assert decode_text(wholes[2]) == "live 2"
        assert read_metadata(wholes[0]).latched


async def test_acl_refusal_and_metrics_over_http(relay: RelayServer) -> None:
    async with client(relay, source="127.0.0.2") as robot, \
            client(relay, token=CAROL_TOKEN) as carol:
        await robot.send(latched("/husky1/map", "secret map"))
        await wait_for(lambda: len(relay.core.latched) == 1)
        assert (await subscribe(carol, ".*"))["type"] == "subscribed"
        await robot.send(string_frame("/husky1/scan", "scan"))
        # The first frame carol gets is the live scan: the map was not hers to receive.
        assert decode_text(await next_binary(carol)) == "scan"
        status, text = await http_get(relay.port, "/metrics")
        assert status == 200
        assert 'fleetctl_latched_events_total{event="stored"} 1' in text
        assert "fleetctl_latched_messages 1" in text
        assert "fleetctl_latched_delivered_frames_total 0" in text


async def test_byte_bound_eviction_through_the_app(
        make_server: Callable[..., RelayServer]) -> None:
    size = len(latched("/husky1/a", "x" * 2000))
    async with make_server(auth=_auth(), limits=ServerLimits(latched_bytes=2 * size)) as relay, \
            client(relay, source="127.0.0.2") as robot:
        for name in "abc":
            await robot.send(latched(f"/husky1/{name}", "x" * 2000))
        await wait_for(lambda: relay.metrics.latched_events.get("stored") == 3)
        assert sorted(relay.core.latched.topics()) == ["/husky1/b", "/husky1/c"]
        assert relay.metrics.latched_events["evicted"] == 1
        async with client(relay, token=ALICE_TOKEN) as viewer:
            await subscribe(viewer, "/husky1/.*")
            got = {read_metadata(await next_binary(viewer)).topic for _ in range(2)}
            assert got == {"/husky1/b", "/husky1/c"}


async def test_keyframe_requests_reach_the_publisher_and_no_one_else(
        relay: RelayServer) -> None:
    async with client(relay, source="127.0.0.2") as husky1, \
            client(relay, source="127.0.0.3") as husky2, \
            client(relay, token=CAROL_TOKEN) as carol, \
            client(relay, token=ALICE_TOKEN) as alice:
        await husky1.send(video("/husky1/camera"))
        await husky2.send(video("/husky2/camera"))
        await wait_for(lambda: len(relay.core.keyframes.video_topics()) == 2)
        await carol.send(encode_keyframe_request("/husky2/camera"))  # not hers to view
        refusal = await next_json(carol, "error")
        assert refusal["code"] == "keyframe_refused" and refusal["topic"] == "/husky2/camera"
        request = encode_keyframe_request("/husky1/camera")
        await alice.send(request)
        assert await next_binary(husky1) == request  # as is, with no subscription
        await alice.send(encode_keyframe_request("/husky2/camera"))
        # husky2's first binary frame is alice's request: carol's never reached it.
        assert decode_keyframe_request(await next_binary(husky2)) == "/husky2/camera"
        assert relay.metrics.keyframe_requests == {"refused": 1, "forwarded": 2}
        await wait_for(lambda: relay.metrics.messages_out.get(KEYFRAME_REQUESTS_TOPIC) == 2)


async def test_a_new_subscription_asks_the_publisher_for_a_keyframe(
        relay: RelayServer) -> None:
    async with client(relay, source="127.0.0.2") as robot, \
            client(relay, token=ALICE_TOKEN) as viewer:
        await robot.send(video("/husky1/camera"))
        await wait_for(lambda: relay.core.keyframes.video_topics() == ["/husky1/camera"])
        await subscribe(viewer, "/husky1/camera")
        asked = await next_binary(robot)
        assert read_metadata(asked).topic == KEYFRAME_REQUESTS_TOPIC
        assert decode_keyframe_request(asked) == "/husky1/camera"
        assert relay.metrics.keyframe_requests == {"auto": 1}


async def test_prefix_and_catch_all_subscribers_get_every_latched_message_of_a_full_store(
        relay: RelayServer) -> None:
    """4,096 latched topics stored (the store's bound): a prefix pattern gets the messages
    of its range, ``.*`` all of them, each once, in the store's order, before live data."""
    topics = [f"/husky1/r{i // 64}/t{i}" for i in range(MAX_ENTRIES)]
    async with client(relay, token=ALICE_TOKEN) as alice:
        for topic in topics:
            await alice.send(latched(topic, topic))
        await wait_for(lambda: len(relay.core.latched) == MAX_ENTRIES, 30.0)
    async with client(relay, source="127.0.0.2") as robot, \
            client(relay, token=BOB_TOKEN) as bob, \
            client(relay, token=ALICE_TOKEN) as everything:
        await next_json(robot, "welcome")
        assert (await subscribe(bob, "/husky1/r7/.*"))["type"] == "subscribed"
        assert (await subscribe(everything, ".*"))["type"] == "subscribed"
        await robot.send(string_frame("/husky1/r7/live", "live", no_drop=True))
        got = [decode_text(await next_binary(bob)) for _ in range(64 + 1)]
        assert got == [*topics[7 * 64:8 * 64], "live"]
        got = [decode_text(await next_binary(everything)) for _ in range(MAX_ENTRIES + 1)]
        assert got == [*topics, "live"]
