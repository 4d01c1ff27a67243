"""The consumer's video viewer with PyAV's real decoder, on frames of the real encoder."""

from __future__ import annotations

import threading
from dataclasses import replace

import pytest

from fleetctl.e2e import videoview
from fleetctl.e2e.samples import Sample

av = pytest.importorskip("av")

from fleetctl.client.syntheticcamera import CameraSequence  # noqa: E402
from fleetctl.client.video import VideoEncoder  # noqa: E402


def _frames(count: int) -> list[tuple[bytes, bool]]:
    camera = CameraSequence(160, 120, 15.0, noise_bank=2)
    enc = VideoEncoder("h264", 160, 120, 15.0, bitrate_bps=300_000)
    out = []
    for i in range(count):
        out += [(f.data, f.keyframe)
                for f in enc.encode(camera.frame(i), i / 15.0, force_keyframe=(i in (0, 8)))]
    return out


def test_a_lost_frame_stops_showing_until_a_keyframe_and_asks_for_one() -> None:
    written: list[Sample] = []
    requests: list[str] = []
    lock = threading.Lock()

    def write(s: Sample) -> None:
        with lock:
            written.append(s)

    viewer = videoview.VideoViewer(write, requests.append)
    frames = _frames(12)
    assert frames[0][1] and frames[8][1] and not frames[3][1]
    for i, (data, key) in enumerate(frames):
        if i == 4:
            continue  # lost on the way
        sample = Sample("/r/cam", i, 0, 0, len(data), "c0", wire_seq=i + 1, keyframe=key)
        viewer.offer(sample, "h264", data)
    viewer.close()
    shown = {s.wire_seq: s.shown_ns is not None for s in written}
    assert [shown[i + 1] for i in range(12) if i != 4] == [
        True, True, True, True, False, False, False, True, True, True, True]
    assert requests == ["/r/cam"]  # once: the next ones come within 0.5 s


def test_no_decoder_records_frames_unshown() -> None:
    written: list[Sample] = []
    viewer = videoview.VideoViewer(written.append, lambda t: None, decoders=lambda c: None)
    s = Sample("/r/cam", 1, 0, 0, 1, "c0", wire_seq=1, keyframe=True)
    viewer.offer(s, "h265", b"x")
    viewer.close()
    assert written == [s] and viewer.unavailable == {"h265"}


def test_a_full_queue_records_the_frame_and_counts_it() -> None:
    gate = threading.Event()
    written: list[Sample] = []

    class Slow:
        codec = "h264"
        waiting_for_keyframe = False

        def decode(self, data: bytes, seq: int | None) -> object:
            gate.wait(10)
            return object()

    viewer = videoview.VideoViewer(written.append, lambda t: None, decoders=lambda c: Slow())
    s = Sample("/r/cam", 1, 0, 0, 1, "c0", wire_seq=1, keyframe=True)
    for i in range(videoview.QUEUE_FRAMES + 5):
        viewer.offer(replace(s, wire_seq=i), "h264", b"x")
    assert viewer.overflow >= 4
    gate.set()
    viewer.close()
    assert len(written) == videoview.QUEUE_FRAMES + 5
