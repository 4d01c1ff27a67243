"""A camera ``publish`` entry with ``video:``: raw images in, CompressedVideo frames out.

The :class:`~fleetctl.client.ros.bridge.Bridge` hands every admitted CDR message of such an
entry to :meth:`VideoTopic.offer`, which only parks it in a slot of one (newest wins, a
replaced message is counted) and wakes the topic's worker thread; decoding the image and
encoding the video happen there, off the asyncio loop and the rclpy executor. The worker:

1. skips the frame (counted) when the link has not taken the previous one yet: encoding it
   would only give the scheduler a frame to drop, and a dropped delta frame breaks every
   frame after it until the next keyframe; skipping before the encoder breaks nothing;
2. reads the image (:mod:`fleetctl.client.videoinput`); an encoding that is not 8-bit
   colour or grey (16UC1 depth, 32FC1, bayer) is logged once per topic and encoding, and
   those messages are relayed unchanged, as the entry's own type, on its remote topic;
3. decides the keyframe: the first frame, a viewer's ``KeyframeRequest`` (via
   :meth:`VideoTopic.request_keyframe`), a new connection of the link, a frame of this
   topic the link dropped since the last one, and every ``keyframe_interval_s``;
4. sets the bitrate once a second from the link (:mod:`fleetctl.client.videorate`);
5. encodes (:class:`fleetctl.client.video.VideoEncoder`) and sends each access unit as a
   ``foxglove_msgs/msg/CompressedVideo`` frame (stamp and frame_id of the image header)
   with the entry's priority, droppable, keyframes marked so the scheduler never drops
   them for frames that depend on them.

When the local PyAV cannot encode the configured codec, one line says so at start and
:meth:`VideoTopic.offer` returns False for every message: the bridge then relays them as
the configured type, as if the entry had no ``video:``.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fleetctl.client.config import PublishSpec
from fleetctl.client.transport import LinkFeedback
from fleetctl.client.video import (
    VIDEO_TYPE,
    Image,
    UnsupportedImage,
    VideoEncoder,
    VideoError,
    codec_problem,
)
from fleetctl.client.videoinput import compressed_image_array, image_array
from fleetctl.client.videorate import BitrateController, LinkSample

log = logging.getLogger(__name__)

__all__ = ["VideoStats", "VideoTopic", "video_topics"]

COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
FPS_HINT = 30.0  # the encoder's frame rate until the image stamps say otherwise (Hz)
_STOP_WAIT_S = 5.0


@dataclass
class VideoStats:
    """Counters of one video topic (plain ints, read from any thread).

    Attributes:
        frames_in: Camera messages offered.
        replaced: Of those, replaced in the slot by a newer one before the worker took
            them (the worker was still encoding).
        skipped_busy: Taken but not encoded: the link had not sent the previous frame.
        relayed: Sent unchanged as the entry's type (unsupported encoding).
        errors: Messages that could not be read or encoded (logged).
        frames_sent: CompressedVideo frames handed to the link.
        keyframes_sent: Of those, keyframes.
        bytes_sent: Bytes of the encoded video data handed to the link.
        keyframe_requests: KeyframeRequests received for this topic.
        bitrate_bps: The encoder's current target bitrate (bits/s).
    """

    frames_in: int = 0
    replaced: int = 0
    skipped_busy: int = 0
    relayed: int = 0
    errors: int = 0
    frames_sent: int = 0
    keyframes_sent: int = 0
    bytes_sent: int = 0
    keyframe_requests: int = 0
    bitrate_bps: int = 0


class VideoTopic:
    """The video path of one ``publish`` entry (see the module docstring).

    Args:
        spec: The entry (``spec.video`` set).
        typestore: The rosbags type store (CDR -> message objects).
        codec: The wire :class:`~fleetctl.wire.codec.Codec`.
        send: ``send(frame, keyframe)``: queue an encoded CompressedVideo frame (any thread).
        relay: ``relay(msg) -> bool``: send a message object unchanged as ``spec.type``.
        next_seq: ``next_seq(remote_topic) -> int``: the topic's next wire sequence number.
        feedback: ``feedback(remote_topic)``: the link's view of the topic; None: no
            adaptation (the bitrate stays at the maximum, keyframes on interval and
            request only).
        clock: Monotonic clock (seconds).
        clock_ns: Wall clock (ns since the epoch) for the frames' publish time.
    """

    def __init__(self, spec: PublishSpec, *, typestore: Any, codec: Any,
                 send: Callable[[bytes, bool], None], relay: Callable[[Any], bool],
                 next_seq: Callable[[str], int],
                 feedback: Callable[[str], LinkFeedback] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 clock_ns: Callable[[], int] = time.time_ns) -> None:
        assert spec.video is not None
        self.spec = spec
        self.video = spec.video
        self.stats = VideoStats()
        self._typestore = typestore
        self._codec = codec
        self._send = send
        self._relay = relay
        self._next_seq = next_seq
        self._feedback = feedback
        self._clock = clock
        self._clock_ns = clock_ns
        self._video_cls = typestore.types[VIDEO_TYPE]
        self._encoder: VideoEncoder | None = None
        self._rate = BitrateController(self.video.min_bitrate_kbps * 1000,
                                       self.video.max_bitrate_kbps * 1000,
                                       in_place=self.video.codec == "h264")
        self._keyframe_wanted = True
        self._seen_dropped = 0
        self._seen_connects: int | None = None
        self._warned: set[str] = set()
        self._slot: bytes | None = None
        self._cond = threading.Condition()
        self._closed = False
        self._worker: threading.Thread | None = None
        self.disabled_reason = codec_problem(self.video.codec)
        if self.disabled_reason is not None:
            log.warning("video: %s: %s: relaying %s messages unchanged instead",
                        spec.topic, self.disabled_reason, spec.type)
            return
        self._worker = threading.Thread(target=self._run, name=f"video {spec.remote_topic}",
                                        daemon=True)
        self._worker.start()

    # -- any thread ---------------------------------------------------------------------

    def offer(self, cdr: bytes) -> bool:
        """Hand one camera message (CDR) to the worker; never blocks.

        Returns:
            False when the video path is off (codec unavailable): relay it instead.
        """
        if self._worker is None:
            return False
        with self._cond:
            if self._slot is not None:
                self.stats.replaced += 1
            self._slot = cdr
            self.stats.frames_in += 1
            self._cond.notify()
        return True

    def request_keyframe(self) -> None:
        """Make the next encoded frame a keyframe (a viewer asked for one)."""
        self.stats.keyframe_requests += 1
        self._keyframe_wanted = True

    def close(self) -> None:
        """Stop the worker and release the encoder (waits for the frame in progress)."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        if self._worker is not None:
            self._worker.join(_STOP_WAIT_S)

    # -- the worker thread --------------------------------------------------------------

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    while self._slot is None and not self._closed:
                        self._cond.wait()
                    if self._closed:
                        return
                    cdr, self._slot = self._slot, None
                if cdr is None:
                    continue
                try:
                    self._process(cdr)
                except Exception as exc:  # one bad frame must never stop the camera
                    self.stats.errors += 1
                    self._keyframe_wanted = True
                    self._warn_once(f"error {type(exc).__name__}", "video: %s: cannot send a "
                                    "frame: %s", self.spec.topic, exc)
        finally:
            if self._encoder is not None:
                self._encoder.close()

    def _process(self, cdr: bytes) -> None:
        sample = self._link_sample()
        if sample is not None and sample.topic.busy:
            self.stats.skipped_busy += 1
            return
        msg = self._typestore.deserialize_cdr(memoryview(cdr), self.spec.type)
        try:
            image, pixel_format = (compressed_image_array(msg)
                                   if self.spec.type == COMPRESSED_IMAGE_TYPE
                                   else image_array(msg))
            # The encoder refuses images too small for video the same way (UnsupportedImage).
            self._encode(msg, image, pixel_format, sample)
        except UnsupportedImage as exc:
            self._warn_once(f"unsupported {exc}", "video: %s: %s: relaying these messages "
                            "unchanged as %s", self.spec.topic, exc, self.spec.type)
            if self._relay(msg):
                self.stats.relayed += 1

    def _encode(self, msg: Any, image: Image, pixel_format: str,
                sample: LinkFeedback | None) -> None:
        now = self._clock()
        encoder = self._encoder_for(image, now, sample)
        force = self._keyframe_due(sample)
        if sample is not None and (bps := self._rate.update(now, _rate_sample(
                sample, self.stats.skipped_busy))) is not None:
            encoder.set_bitrate(bps)
        self.stats.bitrate_bps = encoder.bitrate_bps
        stamp = msg.header.stamp
        stamp_s = stamp.sec + stamp.nanosec * 1e-9
        try:
            frames = encoder.encode(image, stamp_s if stamp_s > 0 else now, force,
                                    pixel_format=pixel_format)
        except VideoError:
            self._keyframe_wanted = True  # what the encoder holds may be inconsistent
            raise
        for frame in frames:
            self._send_frame(msg, frame.data, frame.keyframe)

    def _encoder_for(self, image: Image, now_s: float,
                     sample: LinkFeedback | None) -> VideoEncoder:
        if self._encoder is None:
            height, width = image.shape[:2]
            bitrate = self._rate.start(now_s, _rate_sample(sample, self.stats.skipped_busy)
                                       ) if sample is not None else self._rate.max_bps
            self._encoder = VideoEncoder(
                self.video.codec, width, height, FPS_HINT, bitrate,
                self.video.keyframe_interval_s, max_bitrate_bps=self._rate.max_bps)
        return self._encoder

    def _keyframe_due(self, sample: LinkFeedback | None) -> bool:
        """A viewer asked, the link reconnected, or the link dropped one of our frames."""
        due, self._keyframe_wanted = self._keyframe_wanted, False
        if sample is not None:
            if self._seen_connects is not None and sample.connects != self._seen_connects:
                due = True
            if sample.topic.dropped != self._seen_dropped:
                due = True
            self._seen_connects = sample.connects
            self._seen_dropped = sample.topic.dropped
        return due

    def _send_frame(self, msg: Any, data: bytes, keyframe: bool) -> None:
        video = self._video_cls(timestamp=msg.header.stamp, frame_id=msg.header.frame_id,
                                data=np.frombuffer(data, dtype=np.uint8),
                                format=self.video.codec)
        frame = self._codec.encode(video, VIDEO_TYPE, self.spec.remote_topic,
                                   no_drop=self.spec.no_drop, publish_time_ns=self._clock_ns(),
                                   seq=self._next_seq(self.spec.remote_topic))
        self._send(frame, keyframe)
        self.stats.frames_sent += 1
        self.stats.keyframes_sent += keyframe
        self.stats.bytes_sent += len(data)

    def _link_sample(self) -> LinkFeedback | None:
        return None if self._feedback is None else self._feedback(self.spec.remote_topic)

    def _warn_once(self, key: str, fmt: str, *args: Any) -> None:
        # Once per topic and reason: a 30 Hz camera must not print 30 lines a second.
        if key not in self._warned and len(self._warned) < 64:
            self._warned.add(key)
            log.warning(fmt, *args)


def _rate_sample(sample: LinkFeedback | None, skipped: int) -> LinkSample:
    if sample is None:
        return LinkSample(0.0, 0, 0, skipped)
    topic = sample.topic
    return LinkSample(topic.link_rate_Bps, topic.higher_priority_sent_bytes, topic.dropped,
                      skipped, topic.wire_share)


def video_topics(publish: Sequence[PublishSpec], *, typestore: Any, codec: Any,
                 send: Callable[[PublishSpec, bytes, bool], None],
                 relay: Callable[[PublishSpec, Any], bool], next_seq: Callable[[str], int],
                 feedback: Callable[[str], LinkFeedback] | None) -> dict[str, VideoTopic]:
    """A :class:`VideoTopic` per entry with ``video:``, by remote topic (workers started).

    *send* and *relay* take the entry first (the bridge's ``send_video`` and
    ``send_message``); the rest as :class:`VideoTopic`'s arguments.
    """
    return {
        spec.remote_topic: VideoTopic(
            spec, typestore=typestore, codec=codec,
            send=functools.partial(send, spec), relay=functools.partial(relay, spec),
            next_seq=next_seq, feedback=feedback)
        for spec in publish if spec.video is not None
    }
