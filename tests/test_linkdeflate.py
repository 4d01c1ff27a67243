"""The uplink permessage-deflate: the extension objects alone, and against websockets
servers (the relay: tests/server/test_app_deflate.py)."""

from __future__ import annotations

import asyncio
import os

from websockets import frames
from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import ServerConnection, serve

from fleetctl.batched_connection import BatchedWritesConnection
from fleetctl.linkdeflate import (
    InboundDeflate,
    RelayDeflateFactory,
    RobotDeflateFactory,
    SmallMessageDeflate,
    passes_through,
)


class BatchedClient(BatchedWritesConnection, ClientConnection):
    """The client side, as the robot link composes it."""


def _pair(limit: int = 64) -> tuple[SmallMessageDeflate, InboundDeflate]:
    """A robot-side encoder and relay-side decoder as negotiated (context takeover on the
    robot's direction, none on the relay's)."""
    robot = SmallMessageDeflate(True, False, 15, 15, {"level": 1}, max_message_bytes=limit)
    relay = InboundDeflate(False, True, 15, 15)
    return robot, relay


def _binary(data: bytes, *, fin: bool = True, cont: bool = False) -> frames.Frame:
    return frames.Frame(frames.OP_CONT if cont else frames.OP_BINARY, data, fin)


def test_small_messages_deflated_large_ones_untouched_and_both_decode_in_order() -> None:
    robot, relay = _pair(limit=64)
    small = b"/robot1/pose geometry_msgs/msg/PoseStamped " * 1  # 43 bytes, compressible
    large = os.urandom(200)
    sent = [small, large, small, small, large, small]
    decoded = []
    for data in sent:
        wire = robot.encode(_binary(data))
        if len(data) > 64:
            assert wire.data == data and not wire.rsv1  # as it was, outside the history
        else:
            assert wire.rsv1
        decoded.append(bytes(relay.decode(wire).data))
    assert decoded == sent
    # Back-references to the first copy: later copies cost a few bytes.
    assert len(robot.encode(_binary(small)).data) < len(small) // 4


def test_fragments_follow_the_size_of_their_whole_message() -> None:
    """A fragment of a large message goes raw however small it is; fragments of a small
    message are deflated like the message would be (see SmallMessageDeflate)."""
    from fleetctl.wire.fragments import split
    from tests.support import string_frame

    robot, relay = _pair(limit=4096)
    big = string_frame("/robot1/cloud", "0" * 20_000)
    small = string_frame("/robot1/scan", "1" * 3_000)
    for frame, topic, deflated in ((big, "/robot1/cloud", False),
                                   (small, "/robot1/scan", True)):
        for piece in split(frame, topic=topic, message_id=1, max_fragment_bytes=1024,
                           no_drop=False):
            wire = robot.encode(_binary(piece))
            assert wire.rsv1 == deflated
            assert bytes(relay.decode(wire).data) == piece
    not_a_frame = b"x" * 100  # anything else: its own size decides
    assert robot.encode(_binary(not_a_frame)).rsv1


def test_continuation_follows_the_first_frame_of_its_message() -> None:
    robot, relay = _pair(limit=64)
    for first, rest in ((b"a" * 10, b"b" * 300), (b"c" * 300, b"d" * 10)):
        head = robot.encode(_binary(first, fin=False))
        tail = robot.encode(_binary(rest, cont=True))
        assert head.rsv1 == (len(first) <= 64) and not tail.rsv1
        assert bytes(relay.decode(head).data) + bytes(relay.decode(tail).data) == first + rest


def test_control_frames_and_relay_output_are_never_compressed() -> None:
    robot, relay = _pair()
    ping = frames.Frame(frames.OP_PING, b"12345678")
    assert robot.encode(ping) is ping
    out = _binary(b"x" * 1000)
    assert relay.encode(out) is out
    assert passes_through([relay], 1) and passes_through([], 1)
    assert passes_through([robot], 65) and not passes_through([robot], 64)
    assert not passes_through([object()], 10**6)  # an unknown extension: never bypassed


async def test_robot_against_a_server_without_the_extension() -> None:
    # An older relay (or any websockets server with compression off) answers without the
    # extension: the robot sends plain frames.
    got: list[bytes | str] = []
    done = asyncio.Event()

    async def handler(ws: ServerConnection) -> None:
        async for message in ws:
            got.append(message)
            done.set()

    async with serve(handler, "127.0.0.1", 0, compression=None) as srv:
        port = srv.sockets[0].getsockname()[1]
        async with connect(f"ws://127.0.0.1:{port}", compression=None,
                           extensions=[RobotDeflateFactory()],
                           create_connection=BatchedClient) as ws:
            assert ws.protocol.extensions == []
            await ws.send(b"plain")
            await asyncio.wait_for(done.wait(), 5)
    assert got == [b"plain"]


async def test_browser_style_offer_is_accepted_and_answered_uncompressed() -> None:
    # websockets' default client offer is what browsers send (permessage-deflate with
    # client_max_window_bits): accepted, and the relay's side never compresses.
    sides: list[object] = []

    async def handler(ws: ServerConnection) -> None:
        sides.extend(ws.protocol.extensions)
        await ws.send(b"y" * 1000)

    async with serve(handler, "127.0.0.1", 0, compression=None,
                     extensions=[RelayDeflateFactory()]) as srv:
        port = srv.sockets[0].getsockname()[1]
        async with connect(f"ws://127.0.0.1:{port}") as ws:
            assert await ws.recv() == b"y" * 1000
    assert [type(s) for s in sides] == [InboundDeflate]


def test_on_a_slow_link_every_message_is_deflated_fragments_too() -> None:
    """deflate_all (set by the robot on a slow link, fleetctl.client.slowdeflate): a
    fragment of a large message and a large whole frame are deflated too, their repeated
    metadata becoming back-references; what the relay decodes is byte for byte the same;
    saved_bytes counts what stayed off the wire."""
    from fleetctl.wire import samples
    from fleetctl.wire.codec import default_codec
    from fleetctl.wire.fragments import split

    codec = default_codec()
    image = codec.encode(samples.compressed_image(codec.registry, 20_000),
                         "sensor_msgs/msg/CompressedImage", "/robot1/image", seq=3,
                         publish_time_ns=1_700_000_000_000_000_000)  # random: incompressible
    robot, relay = _pair(limit=4096)
    robot.deflate_all = True
    assert not robot.passes_through(1 << 20)
    pieces = split(image, topic="/robot1/image", message_id=7, max_fragment_bytes=1024,
                   no_drop=False)
    sent = [*pieces, image]
    wire_sizes = []
    for piece in sent:
        wire = robot.encode(_binary(piece))
        assert wire.rsv1
        assert bytes(relay.decode(wire).data) == piece
        wire_sizes.append(len(wire.data))
    assert robot.saved_bytes == sum(map(len, sent)) - sum(wire_sizes)
    # From the second fragment on, most of the ~170 bytes of metadata are a
    # back-reference (the random payload itself does not shrink).
    for piece, size in zip(pieces[1:-1], wire_sizes[1:len(pieces) - 1], strict=True):
        assert size < len(piece) - 110, (size, len(piece))
    robot.deflate_all = False  # and back: the rule by message size again
    wire = robot.encode(_binary(pieces[2]))
    assert not wire.rsv1 and robot.passes_through(1 << 20)
    assert bytes(relay.decode(wire).data) == pieces[2]


def _peer_load_frames(count: int) -> list[bytes]:
    """The e2e peer load's frames in publish order (a 720-beam scan, then two poses)."""
    from fleetctl.e2e import payloads
    from fleetctl.wire.codec import default_codec

    codec = default_codec()
    ts = codec.registry.typestore
    out = []
    for seq in range(count):
        t_ns = 1_700_000_000_000_000_000 + seq * 100_000_000
        for topic, type_name, size in (("/robot1/scan", "sensor_msgs/msg/LaserScan", 5760),
                                       ("/robot1/pose", "geometry_msgs/msg/PoseStamped", 0),
                                       ("/robot1/pose", "geometry_msgs/msg/PoseStamped", 0)):
            msg = payloads.build(ts, type_name, size, seq, t_ns)
            out.append(codec.encode(msg, type_name, topic, seq=seq, publish_time_ns=t_ns))
    return out


def test_fast_link_deflates_with_isal_and_the_relay_inflates_it() -> None:
    """While the link is fast the robot deflates with ISA-L (its level 2): the peer load's
    scans to within 5 % of zlib level 1's size (the relay inflates them byte for byte) and
    its poses to back-references of the previous ones."""
    import zlib

    from isal import isal_zlib

    robot, relay = _pair(limit=16 * 1024)
    assert isinstance(robot.encoder, type(isal_zlib.compressobj(2, wbits=-15)))
    reference = zlib.compressobj(level=1, wbits=-15)
    sent = _peer_load_frames(10)
    ours = zlibs = 0
    for data in sent:
        wire = robot.encode(_binary(data))
        assert wire.rsv1
        assert bytes(relay.decode(wire).data) == data
        ours += len(wire.data)
        zlibs += len(reference.compress(data) + reference.flush(zlib.Z_SYNC_FLUSH)) - 4
    assert ours <= 1.05 * zlibs, (ours, zlibs)
    assert len(robot.encode(_binary(sent[1])).data) < 60  # a pose: back-references


def test_switching_deflaters_at_the_slow_link_rule_keeps_the_stream_decodable() -> None:
    """Fast (ISA-L) -> slow (zlib, three-block fragments) -> fast again, on one stream: each
    switch starts a new context, so no back-reference points into what the other
    deflater compressed; the relay's single inflater reads every message byte for byte."""
    from isal import isal_zlib

    robot, relay = _pair(limit=16 * 1024)
    fast_kind = type(isal_zlib.compressobj(2, wbits=-15))
    sent = _peer_load_frames(12)
    for i, data in enumerate(sent):
        robot.deflate_all = 12 <= i < 24
        wire = robot.encode(_binary(data))
        assert isinstance(robot.encoder, fast_kind) != robot.deflate_all
        assert bytes(relay.decode(wire).data) == data, i
