"""masked_binary_frame against websockets' own serializer and parser (the reference)."""

from __future__ import annotations

import os

import pytest
from websockets.frames import OP_BINARY, Frame
from websockets.streams import StreamReader

from fleetctl.masked_frame import masked_binary_frame, unmasked_binary_header

KEY = b"\x9a\x01\xfe\x37"
LENGTHS = [0, 1, 3, 4, 7, 8, 9, 125, 126, 127, 65535, 65536, 65537, 1_000_003]


def reference(payload: bytes, monkeypatch: pytest.MonkeyPatch) -> bytes:
    monkeypatch.setattr("websockets.frames.secrets.token_bytes", lambda n: KEY)
    return Frame(OP_BINARY, payload).serialize(mask=True)


def parse(frame: bytes) -> Frame:
    reader = StreamReader()
    reader.feed_data(frame)
    reader.feed_eof()
    parser = Frame.parse(reader.read_exact, mask=True)
    try:
        next(parser)
    except StopIteration as done:
        result: Frame = done.value
        return result
    raise AssertionError("frame incomplete")


@pytest.mark.parametrize("length", LENGTHS)
def test_bytes_identical_to_websockets(length: int, monkeypatch: pytest.MonkeyPatch) -> None:
    payload = os.urandom(length)
    assert bytes(masked_binary_frame(payload, KEY)) == reference(payload, monkeypatch)


@pytest.mark.parametrize("offset", [1, 3, 5])
def test_unaligned_view_input(offset: int, monkeypatch: pytest.MonkeyPatch) -> None:
    backing = bytearray(os.urandom(70_001))
    before = bytes(backing)
    view = memoryview(backing)[offset:]
    assert bytes(masked_binary_frame(view, KEY)) == reference(before[offset:], monkeypatch)
    assert backing == before  # masking wrote to the new frame, not into the caller's buffer


@pytest.mark.parametrize("offset", range(8))
@pytest.mark.parametrize("length", [0, 1, 5, 7, 8, 9, 15, 16, 17, 4096 + 3])
def test_every_alignment_and_short_lengths(offset: int, length: int,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    # The bytes before the first aligned word, the words and the tail each take their own
    # path; every source address modulo 8 and lengths around a word exercise all three.
    backing = bytearray(os.urandom(offset + length))
    view = memoryview(backing)[offset:]
    frame = masked_binary_frame(view, KEY)
    assert bytes(frame) == reference(bytes(view), monkeypatch)


def test_fresh_key_each_frame_and_parses_back() -> None:
    payload = os.urandom(4099)
    first, second = masked_binary_frame(payload), masked_binary_frame(payload)
    frame = parse(bytes(first))
    assert frame.opcode is OP_BINARY and frame.fin and frame.data == payload
    assert parse(bytes(second)).data == payload
    assert bytes(first) != bytes(second)  # different keys, different bytes on the wire


def test_bad_key_length() -> None:
    with pytest.raises(ValueError, match="4 bytes"):
        masked_binary_frame(b"x", b"abc")


@pytest.mark.parametrize("length", LENGTHS)
def test_unmasked_header_and_payload_are_websockets_server_frame(length: int) -> None:
    payload = os.urandom(length)
    assert (unmasked_binary_header(length) + payload
            == Frame(OP_BINARY, payload).serialize(mask=False))
