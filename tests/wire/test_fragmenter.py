"""The fast splitter must produce exactly the reference ``split`` output."""

from __future__ import annotations

import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fleetctl.wire.codec import default_codec
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragmenter import fast_split
from fleetctl.wire.fragments import Reassembler, split
from fleetctl.wire.metadata import read_metadata
from tests.support import string_frame


def _frame(topic: str, text: str, *, no_drop: bool = False, seq: int = 0,
           latched: bool = False) -> bytes:
    codec = default_codec()
    return codec.encode(codec.registry.get("std_msgs/msg/String").cls(text),
                        "std_msgs/msg/String", topic, no_drop=no_drop, seq=seq,
                        publish_time_ns=1_700_000_000_000_000_000, latched=latched)


@settings(max_examples=60, deadline=None)
@given(size=st.integers(0, 60_000), max_bytes=st.integers(600, 5000),
       message_id=st.integers(0, 2**64 - 1), no_drop=st.booleans(), seq=st.integers(0, 2**40),
       latched=st.booleans())
def test_fast_split_is_byte_identical_to_split(size: int, max_bytes: int, message_id: int,
                                               no_drop: bool, seq: int, latched: bool) -> None:
    frame = _frame("/r1/points", "p" * size, no_drop=no_drop, seq=seq, latched=latched)
    kw = {"topic": "/r1/points", "message_id": message_id, "max_fragment_bytes": max_bytes,
          "no_drop": no_drop}
    fast = fast_split(frame, **kw)  # type: ignore[arg-type]
    assert fast == split(frame, **kw)  # type: ignore[arg-type]
    assert all(len(f) <= max_bytes for f in fast)
    assert all(read_metadata(f).latched == latched for f in fast)
    reassembler = Reassembler(10**7, 10.0)
    results = [reassembler.feed(f, 0.0) for f in fast]
    assert results[-1] == frame


@settings(max_examples=40, deadline=None)
@given(size=st.integers(0, 60_000), payload=st.integers(1, 5000),
       message_id=st.integers(0, 2**64 - 1), no_drop=st.booleans())
def test_fast_split_by_payload_share_is_byte_identical_to_split(
        size: int, payload: int, message_id: int, no_drop: bool) -> None:
    frame = _frame("/r1/image", "i" * size, no_drop=no_drop, seq=3)
    kw = {"topic": "/r1/image", "message_id": message_id, "max_fragment_bytes": 1024,
          "no_drop": no_drop, "payload_bytes": payload}
    fast = fast_split(frame, **kw)  # type: ignore[arg-type]
    assert fast == split(frame, **kw)  # type: ignore[arg-type]
    reassembler = Reassembler(10**7, 10.0)
    assert [reassembler.feed(f, 0.0) for f in fast][-1] == frame


def test_fast_split_errors_like_split() -> None:
    with pytest.raises(WireError):
        fast_split(b"\x00" * 5000, topic="/a", message_id=1, max_fragment_bytes=1000,
                   no_drop=False)
    frame = string_frame("/a", "x" * 5000)
    with pytest.raises(WireError):
        fast_split(frame, topic="/a", message_id=1, max_fragment_bytes=50, no_drop=False)


def test_fast_split_is_much_cheaper_than_split() -> None:
    frame = string_frame("/r1/points", "p" * 1_000_000)
    kw = {"topic": "/r1/points", "message_id": 1, "max_fragment_bytes": 16384, "no_drop": False}

    def cost(fn: object) -> float:
        best = float("inf")
        for _ in range(3):
            t0 = time.perf_counter()
            fn(frame, **kw)  # type: ignore[operator]
            best = min(best, time.perf_counter() - t0)
        return best

    assert cost(fast_split) * 3 < cost(split)


@pytest.mark.parametrize("count", [2, 3, 4])
@pytest.mark.parametrize(("message_id", "seq"), [(0, 0), (1, 0), (0, 7), (2**64 - 1, 2**63)])
def test_two_three_and_four_fragments_match_split(count: int, message_id: int, seq: int) -> None:
    max_bytes = 2000
    probe = split(string_frame("/t", "q" * 10_000), topic="/t", message_id=message_id,
                  max_fragment_bytes=max_bytes, no_drop=True)
    chunk = 10_000 // len(probe)  # roughly the payload per fragment
    frame = string_frame("/t", "q" * (chunk * count - 300), seq=seq)
    kw = {"topic": "/t", "message_id": message_id, "max_fragment_bytes": max_bytes,
          "no_drop": True}
    reference = split(frame, **kw)  # type: ignore[arg-type]
    for _ in range(2):  # second round: from the template cache
        assert fast_split(frame, **kw) == reference  # type: ignore[arg-type]


def test_latched_and_plain_frames_of_one_shape_do_not_share_templates() -> None:
    """The flag is part of the template key: a cached plain template must not be reused."""
    kw = {"topic": "/r1/map", "message_id": 5, "max_fragment_bytes": 1500, "no_drop": True}
    plain = _frame("/r1/map", "m" * 8000, no_drop=True, seq=4)
    latched = _frame("/r1/map", "m" * 8000, no_drop=True, seq=4, latched=True)
    for frame, flag in ((plain, False), (latched, True), (plain, False)):
        fast = fast_split(frame, **kw)  # type: ignore[arg-type]
        assert fast == split(frame, **kw)  # type: ignore[arg-type]
        assert {read_metadata(f).latched for f in fast} == {flag}
        reassembler = Reassembler(10**7, 10.0)
        assert [reassembler.feed(f, 0.0) for f in fast][-1] == frame
