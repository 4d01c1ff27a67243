"""The relay core routing keyframe requests to video publishers (no sockets)."""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from fleetctl.server.config import ServerConfig, ServerLimits
from fleetctl.server.metrics import Metrics
from fleetctl.server.registry import RobotRegistry
from fleetctl.server.relay import Peer, RelayCore
from fleetctl.wire.codec import default_codec
from fleetctl.wire.control import (
    KEYFRAME_REQUESTS_TOPIC,
    decode_keyframe_request,
    encode_keyframe_request,
    encode_subscription,
)
from fleetctl.wire.samples import header
from tests.server.conftest import ALICE_TOKEN, BOB_TOKEN, auth_map, authed_peer
from tests.support import ManualClock, string_frame

VIDEO = "foxglove_msgs/msg/CompressedVideo"


def make_core(**limits: Any) -> tuple[RelayCore, ManualClock]:
    clock = ManualClock(10.0)
    config = ServerConfig(limits=ServerLimits(**limits))
    return RelayCore(config, auth_map(), RobotRegistry(None, 5.0), Metrics(), clock), clock


def video_frame(topic: str, data: bytes = b"\x00\x00\x01\x41") -> bytes:
    codec = default_codec()
    cls = codec.registry.get(VIDEO).cls
    hdr = header(codec.registry, "camera", stamp_ns=1_700_000_000_000_000_000)
    msg = cls(hdr.stamp, "camera", np.frombuffer(data, dtype=np.uint8), "h264")
    return codec.encode(msg, VIDEO, topic, seq=1)


def requests(p: Peer) -> list[str]:
    return [decode_keyframe_request(f) for t, f in p.outbound.pop_batch(10**9)
            if t == KEYFRAME_REQUESTS_TOPIC and isinstance(f, bytes)]


def errors(p: Peer) -> list[dict[str, Any]]:
    return [m for m in (json.loads(f) for _, f in p.outbound.pop_batch(10**9)
                        if isinstance(f, str)) if m["type"] == "error"]


def setup() -> tuple[RelayCore, ManualClock, Peer, Peer]:
    core, clock = make_core()
    robot, husky2 = authed_peer(core, "127.0.0.2"), authed_peer(core, "127.0.0.3")
    core.on_binary(robot, video_frame("/husky1/camera"))
    core.on_binary(husky2, video_frame("/husky2/camera"))
    return core, clock, robot, husky2


def test_a_request_reaches_the_publisher_only() -> None:
    core, _clock, robot, husky2 = setup()
    bob = authed_peer(core, token=BOB_TOKEN)  # may receive /husky1/.*: no subscription needed
    frame = encode_keyframe_request("/husky1/camera")
    core.on_binary(bob, frame)
    got = [f for t, f in robot.outbound.pop_batch(10**9) if t == KEYFRAME_REQUESTS_TOPIC]
    assert got == [frame]  # forwarded as is
    assert requests(husky2) == [] and requests(bob) == []
    assert core.metrics.keyframe_requests == {"forwarded": 1}


def test_a_request_without_receive_permission_is_refused_once_per_topic() -> None:
    core, clock, _robot, husky2 = setup()
    bob = authed_peer(core, token=BOB_TOKEN)
    errors(bob)
    for _ in range(3):
        core.on_binary(bob, encode_keyframe_request("/husky2/camera"))  # not his
        clock.now_s += 1.0
    assert requests(husky2) == []
    assert [e["code"] for e in errors(bob)] == ["keyframe_refused"]
    assert core.metrics.keyframe_requests == {"refused": 3}


def test_requests_are_rate_limited_per_topic() -> None:
    core, clock, robot, _husky2 = setup()
    alice = authed_peer(core, token=ALICE_TOKEN)
    core.on_binary(robot, video_frame("/husky1/camera2"))
    for _ in range(3):  # three viewers lose the same frame at once
        core.on_binary(alice, encode_keyframe_request("/husky1/camera"))
    core.on_binary(alice, encode_keyframe_request("/husky1/camera2"))
    assert requests(robot) == ["/husky1/camera", "/husky1/camera2"]
    clock.now_s += 0.25
    core.on_binary(alice, encode_keyframe_request("/husky1/camera"))
    assert requests(robot) == ["/husky1/camera"]
    assert core.metrics.keyframe_requests == {"forwarded": 3, "rate_limited": 2}


def test_a_new_subscriber_makes_the_server_ask_for_a_keyframe() -> None:
    core, clock, robot, husky2 = setup()
    alice = authed_peer(core, token=ALICE_TOKEN)
    core.on_binary(alice, encode_subscription("/husky1/.*"))
    assert requests(robot) == ["/husky1/camera"] and requests(husky2) == []
    clock.now_s += 1.0
    core.on_binary(alice, encode_subscription("/husky1/camera"))  # already receives it
    assert requests(robot) == []
    bob = authed_peer(core, token=BOB_TOKEN)
    core.on_binary(bob, encode_subscription(".*"))  # may receive /husky1/.* only
    assert requests(robot) == ["/husky1/camera"] and requests(husky2) == []
    assert core.metrics.keyframe_requests == {"auto": 2}


def test_no_publisher_after_it_closed_and_nothing_learnt_from_other_types() -> None:
    core, _clock, robot, _husky2 = setup()
    core.on_binary(robot, string_frame("/husky1/status_text", "not video"))
    alice = authed_peer(core, token=ALICE_TOKEN)
    core.on_binary(alice, encode_keyframe_request("/husky1/status_text"))
    core.close_peer(robot)
    core.on_binary(alice, encode_keyframe_request("/husky1/camera"))
    assert core.metrics.keyframe_requests == {"no_publisher": 2}


def test_malformed_requests_are_answered_not_forwarded() -> None:
    core, _clock, robot, _husky2 = setup()
    alice = authed_peer(core, token=ALICE_TOKEN)
    errors(alice)
    core.on_binary(alice, string_frame(KEYFRAME_REQUESTS_TOPIC, "/husky1/camera"))
    core.on_binary(alice, encode_keyframe_request(""))
    assert requests(robot) == []
    assert [e["code"] for e in errors(alice)] == ["unknown_type", "malformed_frame"]
    assert core.metrics.keyframe_requests == {"malformed": 2}
