"""Tests of fleetctl.wire.control."""

from __future__ import annotations

import pytest

from fleetctl.wire.codec import Codec
from fleetctl.wire.control import (
    Status,
    Subscription,
    decode_status,
    decode_subscription,
    encode_status,
    encode_subscription,
    known_battery,
)
from fleetctl.wire.errors import WireError
from fleetctl.wire.metadata import read_metadata


@pytest.mark.parametrize("subscribe", [True, False])
def test_subscription_round_trip(subscribe: bool) -> None:
    frame = encode_subscription("/husky[0-9]+/scan", subscribe)
    meta = read_metadata(frame)
    assert (meta.type, meta.topic) == ("amrl_msgs/msg/RobofleetSubscription", "/subscriptions")
    assert decode_subscription(frame) == Subscription("/husky[0-9]+/scan", subscribe)


def test_subscription_with_bad_action_is_rejected(codec: Codec) -> None:
    cls = codec.registry.get("RobofleetSubscription").cls
    frame = codec.encode(cls(".*", 7), "RobofleetSubscription", "/subscriptions")
    with pytest.raises(WireError, match="action must be 0 or 1"):
        decode_subscription(frame)


def test_status_round_trip() -> None:
    frame = encode_status("husky1", status="navigating", is_ok=False, battery_level=0.25,
                          location="dock 3", publish_time_ns=123, seq=9)
    assert read_metadata(frame).topic == "/husky1/status"
    assert decode_status(frame) == Status("husky1", "/husky1/status", "navigating", False,
                                          0.25, "dock 3", 123)


def test_decoding_the_wrong_type_is_a_wire_error() -> None:
    with pytest.raises(WireError, match="expected a amrl_msgs/msg/RobofleetStatus frame"):
        decode_status(encode_subscription(".*"))


def test_status_on_a_non_status_topic_is_rejected(codec: Codec) -> None:
    cls = codec.registry.get("RobofleetStatus").cls
    frame = codec.encode(cls("ok", True, 1.0, ""), "RobofleetStatus", "/a/b/status")
    with pytest.raises(WireError, match="expected /<robot>/status"):
        decode_status(frame)


def test_keyframe_request_round_trip() -> None:
    from fleetctl.wire.control import (
        KEYFRAME_REQUEST_TYPE,
        KEYFRAME_REQUESTS_TOPIC,
        decode_keyframe_request,
        encode_keyframe_request,
    )

    frame = encode_keyframe_request("/husky1/camera", seq=4)
    meta = read_metadata(frame)
    assert (meta.type, meta.topic, meta.no_drop, meta.seq) == (
        KEYFRAME_REQUEST_TYPE, KEYFRAME_REQUESTS_TOPIC, True, 4)
    assert decode_keyframe_request(frame) == "/husky1/camera"
    with pytest.raises(WireError, match="empty"):
        decode_keyframe_request(encode_keyframe_request(""))
    with pytest.raises(WireError):
        decode_keyframe_request(encode_subscription("/x"))


def test_a_negative_or_nan_battery_is_unknown() -> None:
    assert known_battery(-1.0) is None and known_battery(float("nan")) is None
    assert known_battery(float("inf")) is None and known_battery(None) is None
    assert known_battery(0.0) == 0.0 and known_battery(0.5) == 0.5 and known_battery(87.0) == 87.0
