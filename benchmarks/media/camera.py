"""Camera bandwidth and quality: raw Image, JPEG quality 90 and fleetctl video, same frames.

Usage::

    .venv/bin/python benchmarks/media/camera.py [--seconds 10] [--codec h264]
        [--all-codecs] [--json]

The case of the Robot Web Tools paper (section IV-B, Table I): a 640 x 480 camera at 30 Hz
as raw ROS images (12,052 KB/s), MJPEG (1,317 KB/s) and VP8 (342 KB/s).

The frames (:class:`fleetctl.client.syntheticcamera.CameraSequence`, the same every run):
a pan and zoom across a 1279 x 1024 mosaic of four photographs from scikit-image's
packaged data (astronaut, rocket, coffee, chelsea) at their native resolution, zoom
breathing 1.0-1.4, up to ~5 px of motion per frame, plus fresh Gaussian sensor noise of
sigma 2 (8-bit levels) per frame: motion, texture and noise, not a static frame.

Measured per frame, as the wire carries it (``fleetctl.wire.codec.Codec`` frames,
metadata included; KB = 1000 bytes):

- raw: ``sensor_msgs/msg/Image`` rgb8;
- JPEG-90: Pillow (libjpeg-turbo) at quality 90 (4:2:0, as RWT's MJPEG setting), sent as
  ``sensor_msgs/msg/CompressedImage``;
- video: :class:`fleetctl.client.video.VideoEncoder` at the client's defaults (codec
  h264, 1000 kbit/s, a keyframe every 2 s, one thread), sent as
  ``foxglove_msgs/msg/CompressedVideo``, decoded by :class:`fleetctl.client.video.
  VideoDecoder` (PyAV's FFmpeg).

Quality of the decoded frames against the noisy source frames: SSIM
(``skimage.metrics.structural_similarity``, 7 x 7 window) of the luma (BT.601 Y, what
the codecs code at full resolution and what video tools report), and SSIM over R, G, B
(``channel_axis=2``), which also counts the 4:2:0 chroma subsampling both JPEG-90 and
the video use; PSNR over RGB. Every third frame is scored (SSIM costs ~30 ms a frame).
Encode CPU per frame: ``time.process_time`` around the encoder alone (colour conversion
included), on one core (``threads=1``; the machine's other threads idle or not). Latency:
wall time from the frame handed to the encoder to the decoded picture, p50 and p95.

Goals (issue 18): video SSIM >= 0.95, at least 5x smaller than JPEG-90, under 342 KB/s,
encode + decode p50 under 50 ms.
"""

from __future__ import annotations

import argparse
import io
import json
import statistics
import time
from typing import Any

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from fleetctl.client.config import VideoSpec
from fleetctl.client.syntheticcamera import CameraSequence
from fleetctl.client.video import CODECS, VIDEO_TYPE, Image, VideoDecoder, VideoEncoder
from fleetctl.wire.codec import Codec, default_codec

TOPIC = "/robot/camera/image_raw"
WIDTH, HEIGHT, FPS = 640, 480, 30.0
NOISE_SIGMA = 2.0
SCORE_EVERY = 3  # frames between two quality scores
JPEG_QUALITY = 90
RWT_KBPS = {"raw": 12052.0, "mjpeg": 1317.0, "vp8": 342.0}  # RWT Table I
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def luma(rgb: Image) -> np.ndarray:
    """BT.601 luma of an RGB image, float32 in 0..255."""
    return rgb.astype(np.float32) @ _LUMA


class Scores:
    """Quality and cost figures of one encoding of the sequence."""

    def __init__(self) -> None:
        self.frame_bytes: list[int] = []
        self.ssim_y: list[float] = []
        self.ssim_rgb: list[float] = []
        self.psnr: list[float] = []
        self.encode_s: list[float] = []
        self.latency_s: list[float] = []

    def score(self, source: Image, decoded: Image) -> None:
        # scikit-image ships no type hints.
        self.ssim_y.append(float(structural_similarity(  # type: ignore[no-untyped-call]
            luma(source), luma(decoded), data_range=255)))
        self.ssim_rgb.append(float(structural_similarity(  # type: ignore[no-untyped-call]
            source, decoded, channel_axis=2, data_range=255)))
        self.psnr.append(float(peak_signal_noise_ratio(  # type: ignore[no-untyped-call]
            source, decoded, data_range=255)))

    def summary(self, prefix: str, frames: int) -> dict[str, float]:
        kbps = sum(self.frame_bytes) / (frames / FPS) / 1000
        out = {f"{prefix}_kBps": kbps, f"{prefix}_frame_bytes": statistics.mean(
            self.frame_bytes)}
        if self.ssim_y:
            out |= {f"{prefix}_ssim": statistics.mean(self.ssim_y),
                    f"{prefix}_ssim_min": min(self.ssim_y),
                    f"{prefix}_ssim_rgb": statistics.mean(self.ssim_rgb),
                    f"{prefix}_psnr_db": statistics.mean(self.psnr)}
        if self.encode_s:
            out[f"{prefix}_encode_ms"] = statistics.mean(self.encode_s) * 1000
        if self.latency_s:
            ordered = sorted(self.latency_s)
            out[f"{prefix}_latency_p50_ms"] = statistics.median(ordered) * 1000
            out[f"{prefix}_latency_p95_ms"] = ordered[int(0.95 * (len(ordered) - 1))] * 1000
        return out


def _header(codec: Codec, index: int) -> Any:
    types = codec.registry.typestore.types
    ns = int(index / FPS * 1e9)
    stamp = types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    return types["std_msgs/msg/Header"](stamp=stamp, frame_id="camera")


def raw_frame_bytes(codec: Codec, image: Image, index: int) -> int:
    """Wire size of *image* as a ``sensor_msgs/msg/Image`` rgb8 frame."""
    msg = codec.registry.typestore.types["sensor_msgs/msg/Image"](
        header=_header(codec, index), height=HEIGHT, width=WIDTH, encoding="rgb8",
        is_bigendian=0, step=3 * WIDTH, data=image.reshape(-1))
    return len(codec.encode_view(msg, "sensor_msgs/msg/Image", TOPIC, seq=index))


def jpeg_frame(codec: Codec, image: Image, index: int, scores: Scores) -> bytes:
    """JPEG-90 of *image* (encode time recorded) and its CompressedImage frame size."""
    from PIL import Image as PilImage

    started = time.process_time()
    buffer = io.BytesIO()
    PilImage.fromarray(image).save(buffer, format="JPEG", quality=JPEG_QUALITY)
    scores.encode_s.append(time.process_time() - started)
    data = buffer.getvalue()
    msg = codec.registry.typestore.types["sensor_msgs/msg/CompressedImage"](
        header=_header(codec, index), format="jpeg", data=np.frombuffer(data, np.uint8))
    scores.frame_bytes.append(len(codec.encode_view(
        msg, "sensor_msgs/msg/CompressedImage", TOPIC, seq=index)))
    return data


def video_frame_bytes(codec: Codec, data: bytes, video_codec: str, index: int) -> int:
    """Wire size of one access unit as a ``foxglove_msgs/msg/CompressedVideo`` frame."""
    types = codec.registry.typestore.types
    header = _header(codec, index)
    msg = types[VIDEO_TYPE](timestamp=header.stamp, frame_id=header.frame_id,
                            data=np.frombuffer(data, np.uint8), format=video_codec)
    return len(codec.encode_view(msg, VIDEO_TYPE, TOPIC, seq=index))


def measure_video(frames: list[Image], video_codec: str = "h264",
                  bitrate_kbps: int | None = None,
                  keyframe_interval_s: float | None = None) -> dict[str, float]:
    """Encode and decode *frames* as the client does; figures prefixed ``video_``."""
    spec = VideoSpec(codec=video_codec)
    bitrate = 1000 * (bitrate_kbps or spec.max_bitrate_kbps)
    encoder = VideoEncoder(video_codec, WIDTH, HEIGHT, FPS, bitrate,
                           keyframe_interval_s or spec.keyframe_interval_s, threads=1)
    decoder = VideoDecoder(video_codec)
    codec = default_codec()
    scores = Scores()
    keyframes = 0
    for i, image in enumerate(frames):
        started_wall, started_cpu = time.perf_counter(), time.process_time()
        encoded = encoder.encode(image, i / FPS)
        scores.encode_s.append(time.process_time() - started_cpu)
        for frame in encoded:
            keyframes += frame.keyframe
            scores.frame_bytes.append(video_frame_bytes(codec, frame.data, video_codec, i))
            decoded = decoder.decode(frame.data, seq=i)
            if decoded is None:
                raise AssertionError(f"{video_codec}: frame {i} did not decode")
            scores.latency_s.append(time.perf_counter() - started_wall)
            if i % SCORE_EVERY == 0:
                scores.score(image, decoded)
    encoder.close()
    out = scores.summary("video", len(frames))
    out["video_keyframes"] = keyframes
    out["video_bitrate_kbps"] = bitrate / 1000
    return out


def measure_camera(seconds: float = 10.0, codec: str = "h264",
                   all_codecs: bool = False) -> dict[str, Any]:
    """Measure raw, JPEG-90 and video on *seconds* of the camera sequence.

    Args:
        seconds: Length of the sequence at 30 Hz.
        codec: The video codec of the ``video_*`` figures (the client's default: h264).
        all_codecs: Also measure every codec the local PyAV encodes (``codecs``).

    Returns:
        ``raw_kBps``; ``jpeg_*`` and ``video_*``: ``kBps``, ``frame_bytes``, ``ssim``
        (luma), ``ssim_min``, ``ssim_rgb``, ``psnr_db``, ``encode_ms``; ``video_``
        ``latency_p50_ms``/``p95_ms``, ``keyframes``, ``bitrate_kbps``; ``ratio_jpeg_video``,
        ``ratio_raw_video``, ``goals`` (each goal of issue 18: met or not), and the inputs.
    """
    count = round(seconds * FPS)
    camera = CameraSequence(WIDTH, HEIGHT, FPS, NOISE_SIGMA, seed=0)
    frames = [camera.frame(i) for i in range(count)]
    wire = default_codec()
    raw = statistics.mean(raw_frame_bytes(wire, image, i) for i, image in enumerate(frames))
    jpeg = Scores()
    for i, image in enumerate(frames):
        data = jpeg_frame(wire, image, i, jpeg)
        if i % SCORE_EVERY == 0:
            from PIL import Image as PilImage

            jpeg.score(image, np.asarray(PilImage.open(io.BytesIO(data)).convert("RGB")))
    result: dict[str, Any] = {
        "frames": count, "fps": FPS, "width": WIDTH, "height": HEIGHT,
        "noise_sigma": NOISE_SIGMA, "codec": codec,
        "raw_kBps": raw * FPS / 1000, "raw_frame_bytes": raw,
        **jpeg.summary("jpeg", count), **measure_video(frames, codec),
    }
    result["ratio_jpeg_video"] = result["jpeg_kBps"] / result["video_kBps"]
    result["ratio_raw_video"] = result["raw_kBps"] / result["video_kBps"]
    result["goals"] = {
        "video_ssim_ge_0.95": result["video_ssim"] >= 0.95,
        "jpeg_over_video_ge_5": result["ratio_jpeg_video"] >= 5.0,
        "video_under_342_kBps": result["video_kBps"] < RWT_KBPS["vp8"],
        "latency_p50_under_50_ms": result["video_latency_p50_ms"] < 50.0,
    }
    if all_codecs:
        result["codecs"] = {name: measure_video(frames, name) for name in CODECS}
    return result


def _table(r: dict[str, Any]) -> str:
    lines = [f"{r['frames']} frames {r['width']}x{r['height']} at {r['fps']:.0f} Hz, "
             f"noise sigma {r['noise_sigma']}; KB = 1000 bytes",
             f"{'':14}{'KB/s':>9}{'SSIM Y':>8}{'min':>7}{'SSIM RGB':>9}{'PSNR':>7}"
             f"{'enc ms':>8}{'p50 ms':>8}  RWT KB/s",
             f"{'raw Image':14}{r['raw_kBps']:9,.0f}{'':47}  {RWT_KBPS['raw']:,.0f}"]

    def row(name: str, p: str, fig: dict[str, Any], rwt: str) -> str:
        p50 = fig.get(f"{p}_latency_p50_ms")
        return (f"{name:14}{fig[f'{p}_kBps']:9,.1f}{fig[f'{p}_ssim']:8.4f}"
                f"{fig[f'{p}_ssim_min']:7.3f}{fig[f'{p}_ssim_rgb']:9.4f}"
                f"{fig[f'{p}_psnr_db']:7.2f}{fig[f'{p}_encode_ms']:8.2f}"
                f"{'' if p50 is None else f'{p50:.1f}':>8}  {rwt}")

    lines.append(row("JPEG-90", "jpeg", r, f"{RWT_KBPS['mjpeg']:,.0f} (MJPEG)"))
    lines.append(row(f"video {r['codec']}", "video", r, f"{RWT_KBPS['vp8']:,.0f} (VP8)"))
    for name, fig in r.get("codecs", {}).items():
        lines.append(row(f"  {name}", "video", fig, f"{fig['video_keyframes']} keyframes"))
    lines.append(f"JPEG-90 / video {r['ratio_jpeg_video']:.1f}x, raw / video "
                 f"{r['ratio_raw_video']:.0f}x; goals: " + ", ".join(
                     f"{goal} {'met' if ok else 'NOT MET'}" for goal, ok in r["goals"].items()))
    return "\n".join(lines)


def main() -> None:
    """Print the camera table (or JSON)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="sequence length (s)")
    parser.add_argument("--codec", default="h264", choices=sorted(CODECS))
    parser.add_argument("--all-codecs", action="store_true",
                        help="also measure every codec at its defaults")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    args = parser.parse_args()
    result = measure_camera(args.seconds, args.codec, args.all_codecs)
    print(json.dumps(result, indent=2) if args.json else _table(result))


if __name__ == "__main__":
    main()
