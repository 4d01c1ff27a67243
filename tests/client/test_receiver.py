"""The link's receive path in isolation: bad frames, callback errors, reassembly,
decompression, dedupe."""

from __future__ import annotations

import logging

import pytest

from fleetctl.client.receiver import Receiver
from fleetctl.wire.compression import CompressionCodec, compress
from fleetctl.wire.fragments import split
from tests.support import compressed_frame, decode_text, string_frame


def make(received: list[bytes], *, fail: bool = False) -> Receiver:
    def on_frame(frame: bytes) -> None:
        if fail:
            raise ValueError("callback bug")
        received.append(frame)

    return Receiver(lambda: 0.0, on_frame, reassembly_max_bytes=10**6, reassembly_timeout_s=5.0,
                    dedupe_window=100)


def test_malformed_frames_are_counted_and_logged(caplog: pytest.LogCaptureFixture) -> None:
    received: list[bytes] = []
    rx = make(received)
    rx.on_binary(b"\x01\x02")
    rx.on_binary(b"\xff" * 64)
    rx.on_binary(string_frame("/a", "ok"))
    assert [decode_text(f) for f in received] == ["ok"]
    assert rx.stats()["malformed"] == 2
    assert "malformed" in caplog.text


def test_callback_errors_do_not_escape(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.ERROR)
    rx = make([], fail=True)
    rx.on_binary(string_frame("/a", "x"))
    assert rx.stats()["callback_errors"] == 1
    assert "on_frame failed" in caplog.text


def test_fragments_reassemble_and_lost_fragment_is_never_delivered() -> None:
    received: list[bytes] = []
    rx = make(received)
    whole = string_frame("/cloud", "c" * 20_000)
    parts = split(whole, topic="/cloud", message_id=1, max_fragment_bytes=4096, no_drop=False)
    for part in parts[:2] + parts[3:]:  # one fragment lost
        rx.on_binary(part)
    newer = string_frame("/cloud", "d" * 20_000)
    for part in split(newer, topic="/cloud", message_id=2, max_fragment_bytes=4096,
                      no_drop=False):
        rx.on_binary(part)
    assert received == [newer]
    assert rx.stats()["reassembly"]["superseded"] == 1


def test_resends_are_dropped_once_seen() -> None:
    received: list[bytes] = []
    rx = make(received)
    frames = [string_frame("/e", f"s{seq}", no_drop=True, seq=seq) for seq in (1000, 1001)]
    for frame in [*frames, frames[1], frames[0]]:  # resent after a reconnect
        rx.on_binary(frame)
    assert [decode_text(f) for f in received] == ["s1000", "s1001"]
    assert rx.stats()["duplicates"] == 2
    droppable = string_frame("/d", "droppable repeats are not deduped", seq=6)
    rx.on_binary(droppable)
    rx.on_binary(droppable)
    assert len(received) == 4


def test_two_senders_on_one_topic_are_deduped_separately() -> None:
    """A second operator, or a reloaded page whose seq restarts at 1, is not a resend
    (issue 14 item 6): both senders' goals arrive, each sender's resends do not."""
    received: list[bytes] = []
    rx = make(received)
    first = [string_frame("/husky1/goal", f"a{seq}", no_drop=True, seq=seq) for seq in (1, 2, 3)]
    second = [string_frame("/husky1/goal", f"b{seq}", no_drop=True, seq=seq) for seq in (1, 2)]
    for frame in [first[0], first[1], second[0], first[2], second[1]]:
        rx.on_binary(frame)
    for frame in [first[1], second[0]]:  # each sender's resend
        rx.on_binary(frame)
    assert [decode_text(f) for f in received] == ["a1", "a2", "b1", "a3", "b2"]
    assert rx.stats()["duplicates"] == 2


def test_dedupe_memory_is_bounded() -> None:
    received: list[bytes] = []
    rx = Receiver(lambda: 0.0, received.append, reassembly_max_bytes=10**6,
                  reassembly_timeout_s=5.0, dedupe_window=3)
    frames = [string_frame("/e", f"s{i}", no_drop=True, seq=i) for i in range(5)]
    for frame in frames:
        rx.on_binary(frame)
    rx.on_binary(frames[4])  # remembered: dropped
    rx.on_binary(frames[0])  # forgotten (window 3): delivered again
    assert [decode_text(f) for f in received] == ["s0", "s1", "s2", "s3", "s4", "s0"]


def test_compressed_fragments_are_reassembled_then_decompressed() -> None:
    received: list[bytes] = []
    rx = make(received)
    whole = string_frame("/map", "m" * 50_000, no_drop=True, seq=7)
    packed = compress(whole, codec=CompressionCodec.ZSTD, topic="/map", no_drop=True)
    assert len(packed) < 1000
    for part in split(packed, topic="/map", message_id=1, max_fragment_bytes=600, no_drop=True):
        rx.on_binary(part)
    assert received == [whole]
    stats = rx.stats()["decompression"]
    assert stats["decompressed"] == 1 and stats["failed"] == 0
    assert stats["compressed_bytes"] == len(packed)
    assert stats["decompressed_bytes"] == len(whole)
    # Dedupe sees the original's seq: a resend of the same message is dropped.
    rx.on_binary(packed)
    assert len(received) == 1 and rx.stats()["duplicates"] == 1


def test_undecompressible_frames_are_counted_logged_and_never_delivered(
    caplog: pytest.LogCaptureFixture,
) -> None:
    received: list[bytes] = []
    rx = Receiver(lambda: 0.0, received.append, reassembly_max_bytes=10**6,
                  reassembly_timeout_s=5.0, dedupe_window=100, max_decompressed_bytes=20_000)
    big = compress(string_frame("/m", "x" * 30_000), codec=CompressionCodec.DEFLATE,
                   topic="/m", no_drop=False)
    corrupt = compressed_frame("/m", codec=1, original_bytes=100, payload=b"\x00" * 50)
    rx.on_binary(big)  # over max_decompressed_bytes
    rx.on_binary(corrupt)
    rx.on_binary(string_frame("/m", "plain"))
    assert [decode_text(f) for f in received] == ["plain"]
    assert rx.stats()["decompression"]["failed"] == 2
    assert "dropped a compressed frame (1 so far)" in caplog.text
    assert "over the limit of 20000" in caplog.text
