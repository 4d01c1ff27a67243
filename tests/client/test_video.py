"""Unit tests of the PyAV video encoder and decoder, and of the synthetic camera."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from skimage.metrics import structural_similarity

from fleetctl.client.syntheticcamera import CameraSequence, mosaic
from fleetctl.client.threadsched import realtime_threads
from fleetctl.client.video import (
    CODECS,
    CodecUnavailable,
    Image,
    UnsupportedImage,
    VideoDecoder,
    VideoEncoder,
    codec_problem,
    even_size,
)
from fleetctl.client.videobits import is_keyframe

AVAILABLE = [codec for codec in CODECS if codec_problem(codec) is None]
FPS = 30.0


@functools.lru_cache(maxsize=1)
def frames() -> list[Image]:
    """Two seconds of the textured, moving, noisy camera (the benchmark's sequence)."""
    camera = CameraSequence(seed=7)
    return [camera.frame(i) for i in range(60)]


def luma(rgb: Image) -> np.ndarray:
    return rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)


def encode_all(encoder: VideoEncoder, images: list[Image], start: int = 0,
               force: frozenset[int] = frozenset()) -> list[tuple[bytes, bool]]:
    out = []
    for i, image in enumerate(images, start):
        encoded = encoder.encode(image, i / FPS, i in force)
        assert len(encoded) == 1, "low-delay settings give one frame out per frame in"
        out.append((encoded[0].data, encoded[0].keyframe))
    return out


def test_the_wheels_codecs_are_all_there() -> None:
    # PyAV's wheels carry libx264, libvpx and SVT-AV1 (docs/client.md); if one goes
    # missing the client falls back to relaying, and this says so first.
    assert AVAILABLE == ["h264", "vp8", "vp9", "av1"]


@pytest.mark.parametrize("codec", AVAILABLE)
def test_round_trip_keeps_the_picture_at_the_default_bitrate(codec: str) -> None:
    encoder = VideoEncoder(codec, 640, 480, FPS, 1_000_000, 2.0)
    decoder = VideoDecoder(codec)
    scores = []
    total = 0
    for i, (data, keyframe) in enumerate(encode_all(encoder, frames())):
        total += len(data)
        assert is_keyframe(codec, data) == keyframe
        decoded = decoder.decode(data, seq=i)
        assert decoded is not None and decoded.shape == (480, 640, 3)
        if i % 6 == 5:
            scores.append(structural_similarity(  # type: ignore[no-untyped-call]
                luma(frames()[i]), luma(decoded), data_range=255))
    encoder.close()
    assert min(scores) > 0.9, scores
    kbps = total * 8 / (len(frames()) / FPS) / 1000
    assert 500 < kbps < 1500, f"{codec}: {kbps:.0f} kbit/s for a 1000 kbit/s target"
    assert decoder.stats.refused == decoder.stats.errors == 0


@pytest.mark.parametrize("codec", AVAILABLE)
def test_no_encoder_leaves_a_thread_at_real_time_priority(codec: str) -> None:
    # SVT-AV1 sets the thread opening it (and its own) to SCHED_FIFO 99 when it may; the
    # encoder must put them back (fleetctl/client/threadsched.py says why).
    assert realtime_threads() == []
    encoder = VideoEncoder(codec, 320, 240, FPS, 500_000, 2.0, threads=2)
    encode_all(encoder, [image[:240, :320] for image in frames()[:3]])
    encoder.set_bitrate(250_000)  # reopens vp8/vp9/av1
    encode_all(encoder, [image[:240, :320] for image in frames()[3:5]], start=3)
    assert realtime_threads() == []
    encoder.close()


@pytest.mark.parametrize("codec", AVAILABLE)
def test_keyframes_at_start_on_request_and_on_interval(codec: str) -> None:
    encoder = VideoEncoder(codec, 320, 240, FPS, 500_000, keyframe_interval_s=1.0)
    small = [image[:240, :320] for image in frames()[:50]]
    out = encode_all(encoder, small, force=frozenset({10}))
    keyframes = [i for i, (_, key) in enumerate(out) if key]
    # 0: start; 10: forced; 40: one second after the forced one (the interval restarts).
    assert keyframes == [0, 10, 40]
    assert encoder.keyframes == 3
    encoder.close()


def test_odd_sizes_are_cropped_to_even() -> None:
    assert even_size(641, 479) == (640, 478)
    encoder = VideoEncoder("h264", 641, 479)
    assert (encoder.width, encoder.height) == (640, 478)
    image = frames()[0][:479, :641]
    data = encoder.encode(image, 0.0)[0].data
    decoded = VideoDecoder("h264").decode(data)
    assert decoded is not None and decoded.shape == (478, 640, 3)


def test_a_new_image_size_reopens_the_encoder_with_a_keyframe() -> None:
    encoder = VideoEncoder("h264", 320, 240)
    encoder.encode(frames()[0][:240, :320], 0.0)
    assert not encoder.encode(frames()[1][:240, :320], 1 / FPS)[0].keyframe
    bigger = encoder.encode(frames()[2][:480, :640], 2 / FPS)[0]
    assert bigger.keyframe and (encoder.width, encoder.height) == (640, 480)
    assert encoder.reopens == 1


@pytest.mark.parametrize("shape, pixel_format", [
    ((8, 8, 3), "rgb24"),  # too small
    ((64, 64, 2), "rgb24"),  # the array does not fit the format
])
def test_bad_input_raises_unsupported_image(shape: tuple[int, ...], pixel_format: str) -> None:
    encoder = VideoEncoder("h264", 64, 64)
    with pytest.raises(UnsupportedImage):
        encoder.encode(np.zeros(shape, np.uint8), 0.0, pixel_format=pixel_format)


def test_other_pixel_layouts_encode_the_same_picture() -> None:
    rgb = frames()[3][:240, :320]
    decoded = {}
    for name, image in (("rgb24", rgb), ("bgr24", rgb[:, :, ::-1].copy()),
                        ("rgba", np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)]))):
        encoder = VideoEncoder("h264", 320, 240, bitrate_bps=2_000_000)
        out = VideoDecoder("h264").decode(encoder.encode(image, 0.0, pixel_format=name)[0].data)
        assert out is not None
        decoded[name] = out.astype(np.int16)
    # swscale's paths round differently; a swapped channel order would be ~50 levels off.
    assert np.abs(decoded["bgr24"] - decoded["rgb24"]).mean() < 3.0
    assert np.abs(decoded["rgba"] - decoded["rgb24"]).mean() < 3.0
    assert np.abs(decoded["rgb24"] - rgb).mean() < 8.0
    assert np.abs(decoded["rgb24"] - rgb[:, :, ::-1]).mean() > 10.0


def test_unknown_codec_is_refused_with_a_reason() -> None:
    assert "unknown video codec 'h265'" in str(codec_problem("h265"))
    with pytest.raises(CodecUnavailable, match="h265"):
        VideoEncoder("h265", 640, 480)
    with pytest.raises(CodecUnavailable):
        VideoDecoder("mjpeg")


def _rate_kbps(encoder: VideoEncoder, start: int, count: int) -> float:
    sizes = [len(d) for d, _ in encode_all(encoder, frames()[start:start + count], start)]
    return sum(sizes[5:]) * 8 / ((count - 5) / FPS) / 1000


def test_h264_bitrate_changes_in_place_without_a_keyframe() -> None:
    encoder = VideoEncoder("h264", 640, 480, FPS, 1_000_000, 100.0)
    high = _rate_kbps(encoder, 0, 15)
    encoder.set_bitrate(250_000)
    assert encoder.bitrate_bps == 250_000
    out = encode_all(encoder, frames()[15:60], 15)
    assert not any(key for _, key in out), "x264 reconfigures without a keyframe"
    # x264's ABR converges over about a second (docs/client.md): judge the last 0.5 s.
    low = sum(len(d) for d, _ in out[30:]) * 8 / (15 / FPS) / 1000
    assert low < high / 2, (high, low)
    assert encoder.reopens == 0
    encoder.set_bitrate(5_000_000)
    assert encoder.bitrate_bps == encoder.max_bitrate_bps == 1_000_000


def test_vp8_bitrate_change_reopens_with_a_keyframe() -> None:
    encoder = VideoEncoder("vp8", 640, 480, FPS, 1_000_000, 100.0)
    assert not encoder.reconfigures_in_place
    high = _rate_kbps(encoder, 0, 25)
    encoder.set_bitrate(250_000)
    out = encode_all(encoder, frames()[25:50], 25)
    assert [key for _, key in out[:2]] == [True, False]
    assert encoder.reopens == 1
    low = sum(len(d) for d, _ in out[10:]) * 8 / (15 / FPS) / 1000
    assert low < high / 2, (high, low)


def test_frame_counting_encoder_is_retuned_to_the_cameras_rate() -> None:
    """x264 in zero-latency mode counts frames: at 10 Hz it would give a third of the
    bitrate unless told the real rate (once, after 8 frames)."""
    encoder = VideoEncoder("h264", 640, 480, 30.0, 1_000_000, 100.0)
    sizes = [len(encoder.encode(frames()[i], i / 10.0)[0].data) for i in range(40)]
    assert encoder.reopens == 1 and round(encoder.fps_estimate) == 10
    kbps = sum(sizes[20:]) * 8 / 2.0 / 1000
    assert 700 < kbps < 1300, kbps


def test_a_jumping_frame_rate_reopens_the_encoder_at_most_every_few_seconds() -> None:
    """An overloaded robot's camera rate jumps between 5 and 15 Hz: one reopen per jump
    would make a keyframe of every few frames."""
    encoder = VideoEncoder("h264", 320, 240, 30.0, 500_000, 100.0)
    t, images = 0.0, frames()
    for i in range(120):
        t += 1 / 5.0 if (i // 10) % 2 else 1 / 15.0  # 10 frames at 15 Hz, 10 at 5 Hz, ...
        encoder.encode(images[i % len(images)][:240, :320], t)
    # 120 frames over ~16 s: the first retune after 8 frames, then at most one per 5 s.
    assert 1 <= encoder.reopens <= 4, encoder.reopens


def test_decoder_refuses_frames_after_a_gap_until_a_keyframe() -> None:
    encoder = VideoEncoder("h264", 320, 240, FPS, 500_000, 100.0)
    out = encode_all(encoder, [image[:240, :320] for image in frames()[:20]],
                     force=frozenset({12}))
    decoder = VideoDecoder("h264")
    shown = []
    for seq, (data, _) in enumerate(out):
        if seq == 5:
            continue  # lost on the link
        if decoder.decode(data, seq=seq) is not None:
            shown.append(seq)
    assert shown == [0, 1, 2, 3, 4, *range(12, 20)]
    assert decoder.stats.gaps == 1 and decoder.stats.refused == 6


def test_decoder_joining_late_waits_for_a_keyframe() -> None:
    encoder = VideoEncoder("vp9", 320, 240, FPS, 500_000, 100.0)
    out = encode_all(encoder, [image[:240, :320] for image in frames()[:12]],
                     force=frozenset({8}))
    decoder = VideoDecoder("vp9")
    shown = [seq for seq, (data, _) in enumerate(out[3:], 3)
             if decoder.decode(data, seq=seq) is not None]
    assert shown == [8, 9, 10, 11]
    assert decoder.stats.refused == 5 and decoder.stats.gaps == 0


def test_decoder_counts_garbage_and_recovers_at_the_next_keyframe() -> None:
    encoder = VideoEncoder("h264", 320, 240, FPS, 500_000, 100.0)
    out = encode_all(encoder, [image[:240, :320] for image in frames()[:6]],
                     force=frozenset({4}))
    decoder = VideoDecoder("h264")
    assert decoder.decode(out[0][0], 0) is not None
    # A keyframe-looking start (an IDR NAL header) followed by junk.
    assert decoder.decode(b"\x00\x00\x00\x01\x65" + bytes(range(256)) * 4, 1) is None
    assert decoder.decode(out[2][0], 2) is None  # gap: seq 2 follows 1, but 1 was broken
    assert decoder.decode(out[4][0], 4) is not None


def test_camera_sequence_moves_has_texture_and_noise() -> None:
    camera = CameraSequence(seed=1)
    clean0, clean1 = camera.clean(0).astype(np.int16), camera.clean(1).astype(np.int16)
    assert clean0.shape == (480, 640, 3)
    assert np.abs(clean1 - clean0).mean() > 3, "the view moves between frames"
    # Texture: strong local gradients, not a flat or smooth picture.
    assert np.abs(np.diff(clean0, axis=1)).mean() > 3
    noise = camera.frame(0).astype(np.int16) - clean0
    assert 1.7 < noise.std() < 2.3
    assert np.array_equal(CameraSequence(seed=1).frame(5), CameraSequence(seed=1).frame(5))
    banked = CameraSequence(seed=1, noise_bank=4)
    assert 1.7 < (banked.frame(2).astype(np.int16) - camera.clean(2)).std() < 2.3
    assert mosaic().shape == (1024, 1279, 3)
