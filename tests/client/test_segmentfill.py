"""Fragments that fill whole TCP segments once deflated (fleetctl.client.segmentfill):
the arithmetic alone, then with the robot's real deflate on real fragments."""

from __future__ import annotations

import statistics

import pytest
from websockets import frames

from fleetctl.client.segmentfill import (
    ACK_POINT_BYTES,
    DEFAULT_EXTRA_BYTES,
    SLACK_BYTES,
    WS_CLIENT_HEADER_BYTES,
    SegmentFill,
)
from fleetctl.linkdeflate import InboundDeflate, SmallMessageDeflate
from fleetctl.wire import samples
from fleetctl.wire.codec import default_codec
from fleetctl.wire.fragments import split

HEADERS = WS_CLIENT_HEADER_BYTES + ACK_POINT_BYTES + SLACK_BYTES
BOUND = 4 * 1024 * 1024  # the robot's default max_fragment_bytes
T = "/robot1/camera"


def size(fill: SegmentFill, mss: int | None, budget: float, bound: int = BOUND) -> int | None:
    return fill.payload_bytes(T, mss=mss, budget_wire_bytes=budget, max_fragment_bytes=bound)


def test_before_any_fragment_it_assumes_undeflated_metadata_and_an_incompressible_payload(
) -> None:
    fill = SegmentFill()
    assert size(fill, 1368, 1500.0) == 1368 - HEADERS - DEFAULT_EXTRA_BYTES


def test_one_segment_at_least_and_as_many_as_the_budget_holds() -> None:
    fill = SegmentFill()
    fill.observe(T, 1000, 1005, 1025)  # a random payload: a stored block, 20 bytes around it
    one = size(fill, 1448, 100.0)  # a budget under one segment gets one
    assert one == int((1448 - HEADERS - 20) / 1.005)
    assert size(fill, 1448, 1448 * 2.5) == int((2 * 1448 - HEADERS - 20) / 1.005)


def test_a_compressible_payload_gets_a_larger_raw_share_capped() -> None:
    fill = SegmentFill()
    fill.observe(T, 2000, 1200, 1230)  # a cloud's floats: 0.6
    assert size(fill, 1448, 1500.0) == int((1448 - HEADERS - 30) / 0.6)
    zeros = SegmentFill()
    zeros.observe(T, 2000, 20, 50)  # deflates to nothing: at most 4x the room
    assert size(zeros, 1448, 1500.0) == int((1448 - HEADERS - 30) * 4)


def test_near_the_worst_recent_fragment_decides_a_lone_outlier_does_not() -> None:
    """A message's first fragment has a poorer back-reference (module docstring): one in
    ten is not what the middle fragments are sized for; two in ten are."""
    fill = SegmentFill(memory=10)
    for _ in range(9):
        fill.observe(T, 1000, 1005, 1020)
    fill.observe(T, 1000, 600, 700)
    assert fill.extra_bytes(T) == 15 and fill.payload_ratio(T) == pytest.approx(1.005)
    fill.observe(T, 1000, 1008, 1100)  # a second outlier among the last ten
    assert fill.extra_bytes(T) == 92  # the lower of the two
    assert fill.payload_ratio(T) == pytest.approx(1.005)  # one ratio above 1.005 only
    for _ in range(10):  # both leave the memory
        fill.observe(T, 1000, 1005, 1020)
    assert fill.extra_bytes(T) == 15


def test_each_topic_is_sized_by_its_own_fragments_and_the_oldest_is_forgotten() -> None:
    """A camera's JPEG does not deflate, a lidar's cloud does: neither is sized by the
    other's figures; a topic not deflated yet is sized for raw metadata and payload."""
    fill = SegmentFill(max_topics=2)
    for _ in range(5):
        fill.observe("/cam", 1000, 1005, 1020)
        fill.observe("/cloud", 2000, 1200, 1230)
    assert (fill.extra_bytes("/cam"), fill.payload_ratio("/cam")) == (15, pytest.approx(1.005))
    assert (fill.extra_bytes("/cloud"), fill.payload_ratio("/cloud")) == (30, 0.6)
    assert (fill.extra_bytes("/new"), fill.payload_ratio("/new")) == (DEFAULT_EXTRA_BYTES, 1.0)
    fill.observe("/map", 1000, 100, 120)  # a third topic: the least recent one goes
    assert fill.topics() == ["/cloud", "/map"]
    assert fill.extra_bytes("/cam") == DEFAULT_EXTRA_BYTES


def test_the_configured_fragment_bound_holds() -> None:
    """limits.max_fragment_bytes bounds a fragment: segments and raw share both."""
    fill = SegmentFill()
    fill.observe(T, 2000, 20, 50)  # compressible: would ask for 4x the room
    assert size(fill, 1448, 10_000.0, 4096) == 4096 - DEFAULT_EXTRA_BYTES
    assert size(fill, 65483, 10**6, 4096) == 4096 - DEFAULT_EXTRA_BYTES  # loopback
    assert size(fill, 1448, 1500.0, 500) is None  # under 256 bytes of payload


def test_no_mss_or_no_room_leaves_the_scheduler_s_size() -> None:
    fill = SegmentFill()
    assert size(fill, None, 1500.0) is None
    assert size(fill, 0, 1500.0) is None
    assert size(fill, 400, 100.0) is None  # 400 - 34 - 256 < 256


def _deflater() -> tuple[SmallMessageDeflate, InboundDeflate, SegmentFill]:
    robot = SmallMessageDeflate(True, False, 15, 15, {"level": 1}, max_message_bytes=16_384)
    robot.deflate_all = True
    fill = SegmentFill()
    robot.fragment_observer = fill
    return robot, InboundDeflate(False, True, 15, 15), fill


@pytest.mark.parametrize("mss", [1368, 1448])  # over WireGuard; Ethernet with timestamps
@pytest.mark.parametrize("kind", ["image", "cloud"])
def test_real_deflated_fragments_fill_their_segment(mss: int, kind: str) -> None:
    """Message after message of a camera (random bytes) or a lidar (float32 points),
    split by what the deflate of the fragments before reported: once deflated with its
    WebSocket header and an ack point after it, the median middle fragment fills its one
    segment to within 3 %,
    and at most three fragments a message spill into a second packet (the first two, the
    module docstring says why, and a rare middle one whose metadata deflated worse); the
    relay inflates each fragment back byte for byte."""
    codec = default_codec()
    robot, relay, fill = _deflater()
    spare: list[int] = []
    for seq in range(1, 7):
        if kind == "image":
            msg = samples.compressed_image(codec.registry, 60_000, seed=seq)
            type_name = "sensor_msgs/msg/CompressedImage"
        else:
            msg = samples.point_cloud(codec.registry, 4, 1024, seed=seq)
            type_name = "sensor_msgs/msg/PointCloud2"
        frame = codec.encode(msg, type_name, "/robot1/sensor", seq=seq,
                             publish_time_ns=1_700_000_000_000_000_000 + seq)
        payload = fill.payload_bytes("/robot1/sensor", mss=mss, budget_wire_bytes=1500.0,
                                     max_fragment_bytes=BOUND)
        assert payload is not None
        pieces = split(frame, topic="/robot1/sensor", message_id=seq, max_fragment_bytes=1024,
                       no_drop=False, payload_bytes=payload)
        assert len(pieces) > 10
        spilled = 0
        for index, piece in enumerate(pieces):
            wire = robot.encode(frames.Frame(frames.OP_BINARY, piece, True))
            assert bytes(relay.decode(wire).data) == piece
            # with the ack point the link may write after it, in the same segment
            on_wire = len(wire.data) + WS_CLIENT_HEADER_BYTES + ACK_POINT_BYTES
            spilled += on_wire > mss
            if seq > 1 and 1 < index < len(pieces) - 1 and on_wire <= mss:
                spare.append(mss - on_wire)  # the first message was sized before any deflate
        assert spilled <= 3, (seq, spilled, len(pieces))
    assert spare and statistics.median(spare) <= 0.03 * mss, spare
