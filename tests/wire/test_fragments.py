"""Tests of fleetctl.wire.fragments: split and bounded reassembly."""

from __future__ import annotations

import contextlib
import random

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.control import encode_status
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import (
    FRAGMENT_TYPE,
    FragmentHeader,
    Reassembler,
    fragment_payload_span,
    read_fragment_header,
    read_fragment_id,
    split,
)
from fleetctl.wire.metadata import read_metadata, read_root

TOPIC = "/husky1/points"


def _frame(codec: Codec, nbytes: int, topic: str = TOPIC, seed: int = 0) -> bytes:
    cls = codec.registry.get("std_msgs/msg/UInt8MultiArray").cls
    layout = codec.registry.get("std_msgs/msg/MultiArrayLayout").cls([], 0)
    data = np.random.default_rng(seed).integers(0, 256, nbytes, dtype=np.uint8)
    return codec.encode(cls(layout, data), "std_msgs/msg/UInt8MultiArray", topic, seq=5,
                        publish_time_ns=77)


def test_small_frame_is_not_split(codec: Codec) -> None:
    frame = _frame(codec, 100)
    assert split(frame, topic=TOPIC, message_id=1, max_fragment_bytes=1000, no_drop=False) == [
        frame
    ]


@pytest.mark.parametrize("max_bytes", [200, 1000, 16384])
def test_fragments_respect_the_bound_and_carry_metadata(codec: Codec, max_bytes: int) -> None:
    frame = _frame(codec, 50_000)
    parts = split(frame, topic=TOPIC, message_id=9, max_fragment_bytes=max_bytes, no_drop=True)
    assert len(parts) > 1
    assert max(len(p) for p in parts) <= max_bytes
    for index, part in enumerate(parts):
        meta, msg = codec.decode(part)
        assert (meta.type, meta.topic, meta.no_drop, meta.seq) == (FRAGMENT_TYPE, TOPIC, True, 5)
        assert (msg.message_id, msg.index, msg.count, msg.total_bytes) == (
            9, index, len(parts), len(frame)
        )
    assert b"".join(codec.decode(p)[1].payload.tobytes() for p in parts) == frame


def test_payload_bytes_sets_each_fragment_s_share_of_the_frame(codec: Codec) -> None:
    """The robot's segment fill (fleetctl.client.segmentfill): each fragment carries
    *payload_bytes* of the frame, past max_fragment_bytes, which only decides whether
    the frame is split."""
    frame = _frame(codec, 50_000)
    parts = split(frame, topic=TOPIC, message_id=9, max_fragment_bytes=1024, no_drop=False,
                  payload_bytes=1400)
    shares = [len(codec.decode(p)[1].payload) for p in parts]
    assert shares[:-1] == [1400] * (len(parts) - 1) and 0 < shares[-1] <= 1400
    assert len(parts[0]) > 1400
    reasm = Reassembler(max_bytes=1 << 20, timeout_s=5.0)
    assert [reasm.feed(p, now_s=0.0) for p in parts][-1] == frame
    assert split(frame, topic=TOPIC, message_id=9, max_fragment_bytes=len(frame),
                 no_drop=False, payload_bytes=1400) == [frame]
    with pytest.raises(WireError, match="payload_bytes=0 leaves no room"):
        split(frame, topic=TOPIC, message_id=9, max_fragment_bytes=1024, no_drop=False,
              payload_bytes=0)


def test_too_small_fragment_size_is_a_wire_error(codec: Codec) -> None:
    with pytest.raises(WireError, match="leaves no room for payload"):
        split(_frame(codec, 500), topic=TOPIC, message_id=1, max_fragment_bytes=60,
              no_drop=False)


def test_reassembles_in_any_order_with_duplicates(codec: Codec) -> None:
    frame = _frame(codec, 30_000)
    parts = split(frame, topic=TOPIC, message_id=1, max_fragment_bytes=4096, no_drop=False)
    shuffled = parts + parts[:3]
    random.Random(4).shuffle(shuffled)
    reasm = Reassembler(max_bytes=1 << 20, timeout_s=5.0)
    results = [reasm.feed(p, now_s=0.0) for p in shuffled]
    done = [r for r in results if r is not None]
    assert done == [frame]
    assert reasm.stats.completed == 1
    assert reasm.pending_messages == 0 and reasm.pending_bytes == 0


def test_non_fragment_frames_pass_through(codec: Codec) -> None:
    frame = encode_status("r", status="", is_ok=True, battery_level=1.0)
    assert Reassembler(1000, 1.0).feed(frame, 0.0) is frame


def test_loss_then_newer_message_supersedes(codec: Codec) -> None:
    old = split(_frame(codec, 20_000, seed=1), topic=TOPIC, message_id=1,
                max_fragment_bytes=4096, no_drop=False)
    new_frame = _frame(codec, 20_000, seed=2)
    new = split(new_frame, topic=TOPIC, message_id=2, max_fragment_bytes=4096, no_drop=False)
    reasm = Reassembler(max_bytes=1 << 20, timeout_s=5.0)
    for p in old[:-1]:  # the last fragment is lost
        assert reasm.feed(p, 0.0) is None
    results = [reasm.feed(p, 0.1) for p in new]
    assert results[-1] == new_frame
    assert reasm.stats.superseded == 1
    # A late fragment of the superseded message is stale, not a new start.
    assert reasm.feed(old[-1], 0.2) is None
    assert reasm.stats.stale == 1 and reasm.pending_messages == 0


def test_timeout_drops_partial_messages(codec: Codec) -> None:
    parts = split(_frame(codec, 20_000), topic=TOPIC, message_id=1, max_fragment_bytes=4096,
                  no_drop=False)
    reasm = Reassembler(max_bytes=1 << 20, timeout_s=1.0)
    reasm.feed(parts[0], now_s=10.0)
    reasm.expire(now_s=10.5)
    assert reasm.pending_messages == 1
    reasm.expire(now_s=11.5)
    assert reasm.pending_messages == 0 and reasm.stats.timed_out == 1
    # The rest arriving late belongs to a dropped message: stale, nothing is buffered.
    for p in parts[1:]:
        assert reasm.feed(p, now_s=11.6) is None
    assert reasm.stats.stale == len(parts) - 1 and reasm.pending_bytes == 0


def test_byte_bound_is_enforced(codec: Codec) -> None:
    frame = _frame(codec, 20_000)
    parts = split(frame, topic=TOPIC, message_id=1, max_fragment_bytes=4096, no_drop=False)
    small = Reassembler(max_bytes=10_000, timeout_s=1.0)
    assert all(small.feed(p, 0.0) is None for p in parts)
    assert small.stats.over_bytes == len(parts) and small.pending_bytes == 0

    # Two topics that each fit but not together: the older partial is evicted.
    other = split(_frame(codec, 20_000, topic="/b/points"), topic="/b/points", message_id=1,
                  max_fragment_bytes=4096, no_drop=False)
    reasm = Reassembler(max_bytes=len(frame) + 100, timeout_s=1.0)
    reasm.feed(parts[0], 0.0)
    reasm.feed(other[0], 0.0)
    assert reasm.stats.over_bytes == 1 and reasm.pending_messages == 1
    assert reasm.pending_bytes <= len(frame) + 100


def test_message_count_bound_evicts_oldest(codec: Codec) -> None:
    reasm = Reassembler(max_bytes=1 << 24, timeout_s=1.0, max_messages=2)
    for i in range(4):
        topic = f"/r{i}/points"
        parts = split(_frame(codec, 9000, topic=topic), topic=topic, message_id=1,
                      max_fragment_bytes=4096, no_drop=False)
        reasm.feed(parts[0], 0.0)
    assert reasm.pending_messages == 2 and reasm.stats.evicted == 2


def test_inconsistent_and_undecodable_fragments_are_counted(codec: Codec) -> None:
    cls = codec.registry.get(FRAGMENT_TYPE).cls
    payload = np.zeros(10, dtype=np.uint8)

    def frag(message_id: int, index: int, count: int, total: int) -> bytes:
        msg = cls(message_id, index, count, total, payload)
        return codec.encode(msg, FRAGMENT_TYPE, TOPIC)

    reasm = Reassembler(max_bytes=1 << 20, timeout_s=1.0)
    assert reasm.feed(frag(1, 5, 2, 100), 0.0) is None  # index past count
    assert reasm.feed(frag(2, 0, 2, 5), 0.0) is None  # payload larger than total
    assert reasm.feed(frag(3, 0, 2, 100), 0.0) is None
    assert reasm.feed(frag(3, 1, 3, 100), 0.0) is None  # count disagrees with the first
    assert reasm.feed(frag(4, 0, 2, 30), 0.0) is None
    assert reasm.feed(frag(4, 1, 2, 30), 0.0) is None  # complete, but 20 bytes != 30 declared
    # A payload vector whose length runs past the frame: metadata fine, body malformed.
    good = frag(5, 0, 1, 10)
    length_at = good.index(b"\x0a\x00\x00\x00" + bytes(10))
    bad = good[:length_at] + b"\xff\xff\xff\x00" + good[length_at + 4 :]
    assert read_metadata(bad).type == FRAGMENT_TYPE
    assert reasm.feed(bad, 0.0) is None
    assert reasm.stats.malformed == 5
    assert reasm.stats.completed == 0 and reasm.pending_messages == 0


def test_message_whose_own_topic_differs_from_its_fragments_is_refused(codec: Codec) -> None:
    # The server checks permissions on the fragments' topic: a frame for /other smuggled in
    # fragments of TOPIC must never come out of the reassembler.
    smuggled = _frame(codec, 30_000, topic="/husky1/cmd_vel")
    parts = split(smuggled, topic=TOPIC, message_id=1, max_fragment_bytes=4096, no_drop=False)
    assert {read_metadata(p).topic for p in parts} == {TOPIC}
    reasm = Reassembler(max_bytes=1 << 20, timeout_s=5.0)
    assert [r for r in (reasm.feed(p, 0.0) for p in parts) if r is not None] == []
    assert (reasm.stats.malformed, reasm.stats.completed) == (1, 0)


def test_fragments_of_fragments_are_refused(codec: Codec) -> None:
    inner = split(_frame(codec, 30_000), topic=TOPIC, message_id=1, max_fragment_bytes=20_000,
                  no_drop=False)[0]
    parts = split(inner, topic=TOPIC, message_id=2, max_fragment_bytes=4096, no_drop=False)
    reasm = Reassembler(max_bytes=1 << 20, timeout_s=5.0)
    assert [r for r in (reasm.feed(p, 0.0) for p in parts) if r is not None] == []
    assert reasm.stats.malformed == 1


@pytest.mark.parametrize("message_id", [0, 1, 2**64 - 1])
def test_fragment_header_readers_agree_with_the_decoder(codec: Codec, message_id: int) -> None:
    for part in split(_frame(codec, 3000), topic=TOPIC, message_id=message_id,
                      max_fragment_bytes=1000, no_drop=False):
        _meta, root = read_root(part)
        msg = codec.decode_as(part, FRAGMENT_TYPE)[1]
        assert read_fragment_header(part, root) == FragmentHeader(
            msg.message_id, msg.index, msg.count, msg.total_bytes)
        assert read_fragment_id(part, root) == message_id
        start, end = fragment_payload_span(part, root)
        assert part[start:end] == msg.payload.tobytes()


@settings(max_examples=400, deadline=None)
@given(st.data())
def test_fragment_header_readers_raise_only_wire_error(data: st.DataObject) -> None:
    base = split(_frame(default_codec(), 3000), topic=TOPIC, message_id=9,
                 max_fragment_bytes=1000, no_drop=False)
    frame = bytearray(data.draw(st.sampled_from(base)))
    for _ in range(data.draw(st.integers(1, 6))):
        frame[data.draw(st.integers(0, len(frame) - 1))] = data.draw(st.integers(0, 255))
    root = data.draw(st.integers(-4, len(frame) + 4))
    for reader in (read_fragment_header, read_fragment_id, fragment_payload_span):
        with contextlib.suppress(WireError):
            result = reader(bytes(frame), root)
            if reader is fragment_payload_span:  # a span it returns lies in the frame
                assert 0 <= result[0] <= result[1] <= len(frame)
