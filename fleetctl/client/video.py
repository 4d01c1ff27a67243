"""Camera frames to compressed video and back, with PyAV (pure: no rclpy, no I/O).

:class:`VideoEncoder` turns frames (numpy arrays) into the access units that
``foxglove_msgs/msg/CompressedVideo`` carries, one per frame, as Foxglove specifies them:

- **h264** (libx264): Annex B byte stream, SPS and PPS repeated before every IDR
  (``repeat-headers``; no global header), no B-frames, IDR keyframes only (``forced-idr``).
- **vp8** / **vp9** (libvpx): one frame per message, no alt-ref or hidden frames
  (``lag-in-frames`` 0, so no superframes).
- **av1** (SVT-AV1): OBUs (low-overhead format) with the sequence header in every
  keyframe, low-delay prediction (no frame reordering).

Low latency everywhere: no lookahead, no frame reordering, one frame in, one out. Rate
control is ABR with a VBV ceiling at the encoder's maximum bitrate; :meth:`VideoEncoder.
set_bitrate` changes the target in place for h264 (x264 reconfigures its rate control
between frames, no keyframe), while libvpx and SVT-AV1 in this FFmpeg do not take a new
bitrate on an open encoder: there it reopens the encoder and the next frame is a keyframe
(:attr:`VideoEncoder.reconfigures_in_place` says which; the client changes their bitrate
only on large moves, see :mod:`fleetctl.client.videorate`).

Sizes: 4:2:0 needs even width and height, so an odd size is cropped by one pixel (the last
column or row): cheaper than padding and nothing invented at the edge. A frame of another
size than the last one reopens the encoder at the new size (a keyframe).

:class:`VideoDecoder` is the viewer's side for tests, benchmarks and e2e checks: it never
outputs a frame whose reference it did not decode (after a gap in the sequence numbers or a
decode error it waits for the next keyframe, :func:`fleetctl.client.videobits.is_keyframe`).
"""

from __future__ import annotations

import contextlib
import fractions
import logging
import os
import statistics
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from fleetctl.client.threadsched import no_realtime_promotion
from fleetctl.client.videobits import is_keyframe

log = logging.getLogger(__name__)

__all__ = [
    "CODECS", "KEYFRAME_REQUEST_TOPIC", "KEYFRAME_REQUEST_TYPE", "VIDEO_TYPE",
    "CodecUnavailable", "DecoderStats", "EncodedFrame", "UnsupportedImage", "VideoDecoder",
    "VideoEncoder", "VideoError", "codec_problem", "even_size",
]

Image = npt.NDArray[np.uint8]

VIDEO_TYPE = "foxglove_msgs/msg/CompressedVideo"  # what a video topic carries on the wire
# The control topic on which viewers (and the server) ask a video's publisher for a keyframe.
KEYFRAME_REQUEST_TOPIC = "/keyframe_requests"
KEYFRAME_REQUEST_TYPE = "fleetctl_msgs/msg/KeyframeRequest"  # {string topic}

MIN_SIDE_PX = 16  # smaller images are refused (SVT-AV1 and x264 refuse tiny sizes anyway)
_TIME_BASE = fractions.Fraction(1, 90_000)  # the usual video clock: 90 kHz ticks
# VBV buffer as seconds of the maximum bitrate: bounds a keyframe's burst on the link
# (35-50 KB at 1 Mbit/s) while leaving it enough bits to look like the frames around it.
VBV_BUFFER_S = 0.5
# The camera's frame rate is the median of this many recent frame intervals.
_FPS_WINDOW = 15
_FPS_SETTLE_FRAMES = 8  # frames after an (re)open before the rate is judged
_FPS_RETUNE = 0.25  # relative frame rate error that reopens a frame-counting encoder
_FPS_RETUNE_MIN_S = 5.0  # seconds of frames between two such reopens after the first


class VideoError(ValueError):
    """A frame or a codec the video path cannot handle (the message says why)."""


class UnsupportedImage(VideoError):
    """An image encoding or size that is not sent as video (e.g. 16UC1 depth)."""


class CodecUnavailable(VideoError):
    """The local PyAV/FFmpeg has no encoder for the codec."""


@dataclass(frozen=True)
class _Codec:
    encoder: str
    decoder: str
    in_place_bitrate: bool  # takes a new bitrate between frames (else: reopened)
    uses_timestamps: bool  # rate control from timestamps (else: from the frame rate)
    vbv: bool  # takes FFmpeg's maxrate/bufsize
    options: tuple[tuple[str, str], ...]
    # Tried in turn if the encoder refuses the options (an older library on a robot).
    fallback_options: tuple[tuple[str, str], ...] = ()
    decoder_options: tuple[tuple[str, str], ...] = ()


# Encoder settings per CompressedVideo format (benchmarks/media/camera.py measured them:
# docs/client.md, "Video").
CODECS: dict[str, _Codec] = {
    "h264": _Codec("libx264", "h264", True, False, True, (
        ("preset", "veryfast"), ("tune", "zerolatency"),
        # repeat-headers: SPS/PPS before each IDR; forced-idr: a forced keyframe is an IDR
        # (a decoder can start there). Not force-cfr=0: x264 then holds every frame back
        # until the next one's timestamp arrives (a frame interval of latency); the frame
        # rate is given instead (see VideoEncoder._retune_fps).
        ("x264-params", "repeat-headers=1:forced-idr=1:keyint=infinite"),
    )),
    "vp8": _Codec("libvpx", "vp8", False, True, True, (
        ("deadline", "realtime"), ("cpu-used", "8"), ("lag-in-frames", "0"),
        ("auto-alt-ref", "0"),
    )),
    "vp9": _Codec("libvpx-vp9", "vp9", False, True, True, (
        ("deadline", "realtime"), ("cpu-used", "8"), ("lag-in-frames", "0"),
        ("auto-alt-ref", "0"), ("row-mt", "1"),
    )),
    "av1": _Codec("libsvtav1", "libdav1d", False, False, False, (
        # pred-struct=1: low delay (no reordering); rc=2: CBR, the rate control SVT-AV1
        # offers with it; rtc=1: its real-time mode (SVT-AV1 >= 3.0).
        ("preset", "10"), ("svtav1-params", "pred-struct=1:rc=2:rtc=1"),
    ), fallback_options=(("preset", "10"), ("svtav1-params", "pred-struct=1:rc=2")),
        # dav1d holds frames back for its frame threads unless told not to.
        decoder_options=(("max_frame_delay", "1"),)),
}


def codec_problem(codec: str) -> str | None:
    """Why *codec* cannot be encoded here, or None when it can.

    Returns:
        A sentence for a log line, e.g. ``"PyAV's FFmpeg has no libsvtav1 encoder"``.
    """
    info = CODECS.get(codec)
    if info is None:
        return f"unknown video codec {codec!r} (known: {', '.join(CODECS)})"
    import av

    try:
        av.codec.Codec(info.encoder, "w")
    except Exception:  # av's UnknownCodecError; any failure means "not here"
        return f"PyAV's FFmpeg ({av.__version__}) has no {info.encoder} encoder for {codec}"
    return None


def even_size(width: int, height: int) -> tuple[int, int]:
    """The encoded size of a *width* x *height* image: each side cropped to even (pixels).

    Raises:
        UnsupportedImage: A side is under :data:`MIN_SIDE_PX`.
    """
    if width < MIN_SIDE_PX or height < MIN_SIDE_PX:
        raise UnsupportedImage(f"image of {width}x{height} px is too small for video "
                               f"(at least {MIN_SIDE_PX}x{MIN_SIDE_PX})")
    return width & ~1, height & ~1


@dataclass(frozen=True)
class EncodedFrame:
    """One encoded frame (the ``data`` of a CompressedVideo message).

    Attributes:
        data: The access unit.
        keyframe: True when it decodes without earlier frames.
    """

    data: bytes
    keyframe: bool


class VideoEncoder:
    """A low-latency encoder of one camera stream (see the module docstring).

    Args:
        codec: ``h264``, ``vp8``, ``vp9`` or ``av1``.
        width: Image width in pixels (odd sizes are cropped by one).
        height: Image height in pixels.
        fps: Expected frame rate (Hz): a hint for rate control until timestamps say more.
        bitrate_bps: Target bitrate (bits/s).
        keyframe_interval_s: A keyframe at least this often (seconds of timestamps).
        max_bitrate_bps: VBV ceiling (bits/s) and the upper bound of :meth:`set_bitrate`;
            None: *bitrate_bps*.
        threads: Encoder threads; 1 keeps the CPU use of a camera on one core.

    Raises:
        CodecUnavailable: The local PyAV cannot encode *codec*.
        UnsupportedImage: The size is too small.
        VideoError: The encoder refused the settings.
    """

    def __init__(self, codec: str, width: int, height: int, fps: float = 30.0,
                 bitrate_bps: int = 1_000_000, keyframe_interval_s: float = 2.0, *,
                 max_bitrate_bps: int | None = None, threads: int = 1) -> None:
        problem = codec_problem(codec)
        if problem is not None:
            raise CodecUnavailable(problem)
        if codec == "av1":
            # SVT-AV1 prints its whole configuration at INFO on stderr for every open
            # (and reopen), and warnings such as "TPL is disabled in low delay"; errors show.
            os.environ.setdefault("SVT_LOG", "1")
        self.codec = codec
        self._info = CODECS[codec]
        self.width, self.height = even_size(width, height)
        self.keyframe_interval_s = keyframe_interval_s
        self.max_bitrate_bps = max(1, max_bitrate_bps or bitrate_bps)
        self._bitrate_bps = min(max(1, bitrate_bps), self.max_bitrate_bps)
        self._threads = threads
        self._fps = fps
        self._last_pts: int | None = None
        self._last_pts_s: float | None = None
        self._first_pts_s: float | None = None
        self._last_key_s: float | None = None
        self._force_next = True
        self.reopens = 0
        self._fps_retunes = 0
        self.frames_in = 0
        self.keyframes = 0
        self._opened_fps = fps
        self._frames_since_open = 0
        self._intervals: deque[float] = deque(maxlen=_FPS_WINDOW)
        self._ctx: Any = self._open()

    @property
    def reconfigures_in_place(self) -> bool:
        """True when :meth:`set_bitrate` keeps the stream going (no keyframe)."""
        return self._info.in_place_bitrate

    @property
    def bitrate_bps(self) -> int:
        """The current target bitrate (bits/s)."""
        return self._bitrate_bps

    @property
    def fps_estimate(self) -> float:
        """The camera's frame rate from the timestamps (Hz; the *fps* hint before two
        frames)."""
        return self._fps

    def _open(self) -> Any:
        """A new encoder context at the current size, bitrate and frame rate."""
        info = self._info
        attempts = [info.options] + ([info.fallback_options] if info.fallback_options else [])
        error: Exception | None = None
        for options in attempts:
            try:
                ctx = self._context(dict(options))
            except Exception as exc:
                error = exc
                continue
            self._opened_fps = self._fps
            self._frames_since_open = 0
            return ctx
        raise VideoError(f"{info.encoder} refused {self.width}x{self.height} at "
                         f"{self._bitrate_bps} bit/s: {error}") from error

    def _context(self, options: dict[str, str]) -> Any:
        import av

        ctx: Any = av.CodecContext.create(self._info.encoder, "w")
        ctx.width, ctx.height = self.width, self.height
        ctx.pix_fmt = "yuv420p"
        ctx.time_base = _TIME_BASE
        ctx.framerate = fractions.Fraction(max(1, round(self._fps * 1000)), 1000)
        ctx.bit_rate = self._bitrate_bps
        ctx.gop_size = 1 << 30  # keyframes are ours to place (interval, requests, losses)
        ctx.max_b_frames = 0
        ctx.thread_count = self._threads
        if self._info.vbv:
            vbv = self.max_bitrate_bps
            options.update(maxrate=str(vbv), bufsize=str(int(vbv * VBV_BUFFER_S)))
        if self.codec == "av1":
            # SVT-AV1 takes its threads as "lp" (logical processors), not thread_count.
            options["svtav1-params"] += f":lp={self._threads}"
        ctx.options = options
        with no_realtime_promotion(self._info.encoder):
            ctx.open()
        return ctx

    def set_bitrate(self, bps: int) -> None:
        """Set the target bitrate (bits/s), at most ``max_bitrate_bps``.

        h264 changes it between two frames; the other codecs reopen the encoder, so the
        next frame is a keyframe (counted in :attr:`reopens`).
        """
        bps = min(max(1, int(bps)), self.max_bitrate_bps)
        if bps == self._bitrate_bps:
            return
        self._bitrate_bps = bps
        if self._info.in_place_bitrate:
            # x264 compares this with its rate control at the next frame and reconfigures
            # in place (FFmpeg's libx264 reconfig_encoder; allowed because VBV is on).
            self._ctx.bit_rate = bps
        else:
            self._reopen()

    def _reopen(self) -> None:
        self.close()
        self._ctx = self._open()
        self.reopens += 1
        self._force_next = True

    def encode(self, image: Image, pts_s: float, force_keyframe: bool = False, *,
               pixel_format: str = "rgb24") -> list[EncodedFrame]:
        """Encode one frame.

        Args:
            image: ``H x W x 3`` uint8 RGB (or the layout of *pixel_format*: ``bgr24``,
                ``rgba``, ``bgra`` ``H x W x 4``, ``gray`` ``H x W``, ``yuyv422``
                ``H x W x 2``). An odd side is cropped by one pixel; another size than
                the encoder's reopens it (keyframe).
            pts_s: Capture time in seconds (the image header's stamp); decides the
                periodic keyframes and, for h264/vp8/vp9, the rate control's frame rate.
            force_keyframe: Make this frame a keyframe.
            pixel_format: PyAV's name of the layout of *image*.

        Returns:
            The encoded frames: one per call with these low-delay settings (the list form
            keeps a codec that buffers honest).

        Raises:
            UnsupportedImage: The image is too small or its shape does not fit
                *pixel_format*.
            VideoError: The encoder failed on this frame.
        """
        import av
        from av.video.frame import PictureType

        height, width = image.shape[:2]
        size = even_size(width, height)
        if size != (self.width, self.height):
            self.width, self.height = size
            self._reopen()
        if (height, width) != (self.height, self.width):
            image = image[:self.height, :self.width]
        try:
            frame = av.VideoFrame.from_ndarray(image, format=pixel_format)
        except (ValueError, TypeError) as exc:
            raise UnsupportedImage(f"a {image.shape} {image.dtype} array is not "
                                   f"{pixel_format}: {exc}") from exc
        frame = frame.reformat(format="yuv420p")
        frame.pts = self._pts(pts_s)
        self._retune_fps()
        if self._keyframe_due(pts_s) or force_keyframe:
            frame.pict_type = PictureType.I
            self._last_key_s = pts_s
        # An encoder may start more threads at its first frame: guard that one too.
        guard = (no_realtime_promotion(self._info.encoder) if self._frames_since_open == 0
                 else contextlib.nullcontext())
        try:
            with guard:
                packets = self._ctx.encode(frame)
        except Exception as exc:
            raise VideoError(f"{self._info.encoder} failed on a frame: {exc}") from exc
        self.frames_in += 1
        out = [EncodedFrame(bytes(p), bool(p.is_keyframe)) for p in packets]
        self.keyframes += sum(encoded.keyframe for encoded in out)
        return out

    def _keyframe_due(self, pts_s: float) -> bool:
        last = self._last_key_s
        # A timestamp going backwards (a restarted bag, a camera clock reset) starts over.
        due = (self._force_next or last is None or pts_s < last
               or pts_s - last >= self.keyframe_interval_s)
        self._force_next = False
        return due

    def _retune_fps(self) -> None:
        """Reopen a codec whose rate control counts frames, not time (x264 in its
        zero-latency mode, SVT-AV1), when the camera's rate is off the one it was given by
        more than a quarter: at 10 Hz instead of 30 its bitrate would be a third of the
        target. Once the estimate settled (8 frames); the reopen costs one keyframe."""
        self._frames_since_open += 1
        # The first retune comes once the estimate settled; later ones at most every
        # _FPS_RETUNE_MIN_S of frames: an overloaded robot's rate jumps around, and a reopen
        # per jump would make every other frame a keyframe.
        settle = _FPS_SETTLE_FRAMES if self._fps_retunes == 0 else max(
            _FPS_SETTLE_FRAMES, int(self._opened_fps * _FPS_RETUNE_MIN_S))
        if self._info.uses_timestamps or self._frames_since_open < settle:
            return
        if abs(self._fps / self._opened_fps - 1.0) > _FPS_RETUNE:
            log.info("%s: the camera runs at %.1f Hz, not %.1f: reopening the encoder",
                     self._info.encoder, self._fps, self._opened_fps)
            self._fps_retunes += 1
            self._reopen()

    def _pts(self, pts_s: float) -> int:
        """Encoder ticks of *pts_s*, strictly increasing (encoders refuse anything else)."""
        if self._first_pts_s is None:
            self._first_pts_s = pts_s
        if self._last_pts_s is not None and pts_s > self._last_pts_s:
            self._intervals.append(pts_s - self._last_pts_s)
            # The median ignores a dropped frame's double interval.
            self._fps = 1.0 / statistics.median(self._intervals)
        self._last_pts_s = pts_s
        pts = round((pts_s - self._first_pts_s) / _TIME_BASE)
        if self._last_pts is not None and pts <= self._last_pts:
            pts = self._last_pts + round(1 / (self._fps * _TIME_BASE))
        self._last_pts = pts
        return pts

    def close(self) -> None:
        """Flush and release the encoder (frames still inside are discarded)."""
        ctx = self._ctx
        if ctx is None:
            return
        self._ctx = None
        try:
            # SVT-AV1 complains on stderr when closed without the end-of-stream signal.
            ctx.encode(None)
        except Exception as exc:  # closing must never fail the caller
            log.debug("flushing %s: %s", self._info.encoder, exc)
        self._last_pts = None
        self._first_pts_s = None


@dataclass
class DecoderStats:
    """Counters of a :class:`VideoDecoder`.

    Attributes:
        decoded: Frames output.
        refused: Frames not decoded because a reference was missing (waiting for a
            keyframe after the start, a sequence gap or an error).
        gaps: Gaps seen in the sequence numbers.
        errors: Frames the decoder failed on.
    """

    decoded: int = 0
    refused: int = 0
    gaps: int = 0
    errors: int = 0


class VideoDecoder:
    """Decodes a CompressedVideo stream and refuses frames whose reference was lost.

    Args:
        codec: The stream's ``format`` (``h264``, ``vp8``, ``vp9``, ``av1``).

    Raises:
        CodecUnavailable: No decoder for *codec* here.
    """

    def __init__(self, codec: str) -> None:
        import av

        info = CODECS.get(codec)
        if info is None:
            raise CodecUnavailable(f"unknown video codec {codec!r}")
        try:
            self._ctx: Any = av.CodecContext.create(info.decoder, "r")
        except Exception as exc:
            raise CodecUnavailable(f"PyAV has no {info.decoder} decoder: {exc}") from exc
        # One thread: FFmpeg's frame threads hold a frame back per thread (latency).
        self._ctx.thread_count = 1
        self._ctx.options = dict(info.decoder_options)
        self.codec = codec
        self.stats = DecoderStats()
        self._last_seq: int | None = None
        self._need_keyframe = True

    @property
    def waiting_for_keyframe(self) -> bool:
        """Frames are refused until the next keyframe (the start, a gap, an error)."""
        return self._need_keyframe

    def decode(self, data: bytes, seq: int | None = None) -> Image | None:
        """Decode one frame to ``H x W x 3`` RGB, or refuse it.

        Args:
            data: One CompressedVideo ``data``.
            seq: The frame's sequence number (wire metadata ``seq``); a jump of more than
                one means frames were lost, so frames are refused until a keyframe.

        Returns:
            The image, or None when refused (counted) or when the decoder held it back.
        """
        if seq is not None:
            if self._last_seq is not None and seq != self._last_seq + 1:
                self.stats.gaps += 1
                self._need_keyframe = True
            self._last_seq = seq
        if self._need_keyframe:
            if not is_keyframe(self.codec, data):
                self.stats.refused += 1
                return None
            self._need_keyframe = False
        import av

        try:
            frames = self._ctx.decode(av.Packet(data))
        except Exception as exc:  # av.error.InvalidDataError and friends: a broken frame
            self.stats.errors += 1
            self._need_keyframe = True
            log.debug("%s decoder failed: %s", self.codec, exc)
            return None
        if not frames:
            return None
        self.stats.decoded += len(frames)
        rgb: Image = frames[-1].to_ndarray(format="rgb24")
        return rgb
