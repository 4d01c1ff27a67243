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


def test_dedupe_window_accepts_a_restarted_sender() -> None:
    received: list[bytes] = []
    rx = make(received)
    for seq in (1000, 1001, 1001, 999, 5, 6):  # 5: far below -> a restarted sender
        rx.on_binary(string_frame("/e", f"s{seq}", no_drop=True, seq=seq))
    assert [decode_text(f) for f in received] == ["s1000", "s1001", "s5", "s6"]
    assert rx.stats()["duplicates"] == 2
    rx.on_binary(string_frame("/d", "droppable repeats are not deduped", seq=6))
    rx.on_binary(string_frame("/d", "droppable repeats are not deduped", seq=6))
    assert len(received) == 6


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
