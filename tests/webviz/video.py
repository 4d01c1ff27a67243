"""Real encoded video for the page's tests: frames encoded with PyAV (libx264, libvpx,
libvpx-vp9, SVT-AV1, x265) as a robot's video topic carries them (Foxglove's
CompressedVideo rules: Annex B with SPS/PPS in every keyframe, no B-frames)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import av
import numpy as np

from fleetctl.client.threadsched import no_realtime_promotion

ENCODERS = {
    "h264": ("libx264", {"preset": "ultrafast", "tune": "zerolatency",
                         "x264-params": "repeat-headers=1:bframes=0"}),
    "vp8": ("libvpx", {"deadline": "realtime", "cpu-used": "8", "lag-in-frames": "0"}),
    "vp9": ("libvpx-vp9", {"deadline": "realtime", "cpu-used": "8", "lag-in-frames": "0"}),
    # Low delay (no reordering) needs constant bitrate in SVT-AV1 4.x.
    "av1": ("libsvtav1", {"preset": "10", "svtav1-params": "pred-struct=1:rc=2"}),
    "h265": ("libx265", {"preset": "ultrafast", "tune": "zerolatency",
                         "x265-params": "bframes=0:log-level=error"}),
}


@dataclass(frozen=True)
class EncodedUnit:
    """One encoded access unit / temporal unit.

    Attributes:
        data: The bytes a CompressedVideo message carries.
        key: The encoder marked it a keyframe.
    """

    data: bytes
    key: bool


def picture(i: int, width: int, height: int) -> np.ndarray:
    """A moving, textured RGB picture (a gradient and a bright square sliding right)."""
    yy, xx = np.mgrid[0:height, 0:width]
    rgb = np.zeros((height, width, 3), dtype=np.uint8)
    rgb[..., 0] = (xx * 255 // max(1, width - 1)).astype(np.uint8)
    rgb[..., 1] = 120 + ((xx // 8 + yy // 8) % 2) * 60
    rgb[..., 2] = (yy * 255 // max(1, height - 1)).astype(np.uint8)
    x0 = (8 * i) % max(1, width - 40)
    rgb[height // 3 : height // 3 + 40, x0 : x0 + 40] = 255
    return rgb


def photo(i: int, width: int, height: int) -> np.ndarray:
    """A slow pan across a real photograph (scikit-image's astronaut, 512 x 512)."""
    from skimage.data import astronaut

    img: np.ndarray = astronaut()  # type: ignore[no-untyped-call]
    x0 = (2 * i) % max(1, img.shape[1] - width)
    return np.ascontiguousarray(img[: min(height, img.shape[0]), x0 : x0 + width])


def encode(fmt: str, frames: int, *, width: int = 320, height: int = 240,
           keyframe_every: int = 10, source: str = "picture") -> list[EncodedUnit]:
    """Encode *frames* pictures with the encoder a robot would use for *fmt*.

    Args:
        fmt: ``h264``, ``vp8``, ``vp9``, ``av1`` or ``h265``.
        frames: Pictures to encode (one unit each, flushed at the end).
        width: Picture width (pixels, even).
        height: Picture height (pixels, even).
        keyframe_every: GOP length (frames).
        source: ``picture`` (synthetic, any size) or ``photo`` (at most 512 x 512).
    """
    draw = photo if source == "photo" else picture
    name, options = ENCODERS[fmt]
    logging.getLogger("libav").setLevel(logging.ERROR)
    ctx: Any = av.CodecContext.create(name, "w")  # a VideoCodecContext; PyAV's stubs say less
    ctx.width, ctx.height, ctx.pix_fmt = width, height, "yuv420p"
    ctx.time_base = Fraction(1, 30)
    ctx.framerate = Fraction(30)
    ctx.gop_size = keyframe_every
    ctx.bit_rate = 800_000
    ctx.options = dict(options)
    out: list[EncodedUnit] = []
    # SVT-AV1 raises its threads and this one to SCHED_FIFO 99 (threadsched.py says why
    # that must not outlive the encoder): the same guard as the robot's encoder.
    with no_realtime_promotion(name):
        for i in range(frames):
            frame = av.VideoFrame.from_ndarray(draw(i, width, height), format="rgb24")
            frame = frame.reformat(format="yuv420p")
            frame.pts = i
            out += [EncodedUnit(bytes(p), bool(p.is_keyframe)) for p in ctx.encode(frame)]
        out += [EncodedUnit(bytes(p), bool(p.is_keyframe)) for p in ctx.encode(None)]
    return out


def h264_codec_string(unit: bytes) -> str | None:
    """``avc1.PPCCLL`` from the first SPS NAL unit (reference for the page's parser)."""
    at = unit.find(b"\x00\x00\x01\x67")
    if at < 0:
        return None
    p, c, level = unit[at + 4 : at + 7]
    return f"avc1.{p:02X}{c:02X}{level:02X}"
