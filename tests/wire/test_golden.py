"""Golden byte fixtures: the wire format does not change by accident."""

from __future__ import annotations

import pytest

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.metadata import read_metadata

from .golden import FIXTURES, golden_cases

CASES = golden_cases(default_codec())


@pytest.mark.parametrize("stem", sorted(CASES))
def test_encoder_writes_the_golden_bytes(codec: Codec, stem: str) -> None:
    type_name, topic, msg, kwargs = CASES[stem]
    expected = FIXTURES.joinpath(f"{stem}.bin").read_bytes()
    assert codec.encode(msg, type_name, topic, **kwargs) == expected


@pytest.mark.parametrize("stem", sorted(CASES))
def test_golden_bytes_decode_to_the_message(codec: Codec, stem: str) -> None:
    type_name, topic, msg, _kwargs = CASES[stem]
    frame = FIXTURES.joinpath(f"{stem}.bin").read_bytes()
    meta, back = codec.decode(frame)
    assert (meta.type, meta.topic) == (type_name, topic)
    assert read_metadata(frame) == meta
    ts = codec.registry.typestore
    assert ts.serialize_cdr(back, type_name) == ts.serialize_cdr(msg, type_name)


def test_robofleet_subscription_bytes_are_readable_by_hand() -> None:
    """Robofleet readers only know fields 0 (type) and 1 (topic) of ``__metadata``."""
    frame = FIXTURES.joinpath("robofleet_subscription.bin").read_bytes()
    assert b"amrl_msgs/msg/RobofleetSubscription\x00" in frame
    assert b"/subscriptions\x00" in frame and b"/husky1/.*\x00" in frame
