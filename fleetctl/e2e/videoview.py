"""The e2e consumer's video viewer: decodes each video topic as the web page does.

A frame is decoded by :class:`fleetctl.client.video.VideoDecoder`, which refuses every
frame after a gap in the metadata ``seq`` (or a decoder error) until the next keyframe, and
while it waits the viewer asks the robot for one on ``/keyframe_requests`` at most every
:data:`REQUEST_INTERVAL_S`, as the page's ``VideoGate`` does. Each frame's sample records
when it was shown (``shown_ns``) or that it was refused (None); the e2e analysis then
checks, independently of the decoder, that no shown frame had a broken reference chain.

Decoding runs on a worker thread so that it never delays the receipt time of other frames
on the consumer's event loop. Its queue is bounded (:data:`QUEUE_FRAMES`): a frame that does
not fit is recorded as refused and counted, and the decoder sees the gap it leaves.
"""

from __future__ import annotations

import queue
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from fleetctl.e2e.samples import Sample

QUEUE_FRAMES = 256  # ~17 s of a 15 Hz camera: only a stalled decoder fills it
REQUEST_INTERVAL_S = 0.5  # the page's VideoGate.REQUEST_INTERVAL_MS

Write = Callable[[Sample], None]
Request = Callable[[str], None]  # ask for a keyframe on this topic (thread-safe)


class VideoViewer:
    """Decodes video frames off the receiving loop and writes their samples.

    Args:
        write: Writes one sample (called from the worker thread).
        request: Sends a keyframe request for a topic (must be thread-safe).
        decoders: Makes a decoder for a codec name (tests inject one); default
            :class:`~fleetctl.client.video.VideoDecoder`, None when PyAV is missing.
    """

    def __init__(self, write: Write, request: Request,
                 decoders: Callable[[str], Any] | None = None) -> None:
        self._write = write
        self._request = request
        self._make = decoders or _pyav_decoder
        self._decoders: dict[str, Any] = {}
        self._last_request: dict[str, float] = {}
        self._queue: queue.Queue[tuple[Sample, str, bytes] | None] = queue.Queue(QUEUE_FRAMES)
        self.overflow = 0  # frames recorded unseen because the queue was full
        self.unavailable: set[str] = set()  # codecs with no decoder here
        self._thread = threading.Thread(target=self._run, name="video-viewer", daemon=True)
        self._thread.start()

    def offer(self, sample: Sample, codec: str, data: bytes) -> None:
        """Queue one frame (its sample has ``wire_seq`` and ``keyframe`` set)."""
        try:
            self._queue.put_nowait((sample, codec, data))
        except queue.Full:
            self.overflow += 1
            self._write(sample)

    def close(self, timeout_s: float = 5.0) -> None:
        """Decode what is queued (bounded by *timeout_s*), then stop the worker."""
        try:
            self._queue.put(None, timeout=timeout_s)
        except queue.Full:
            return
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            sample, codec, data = item
            self._write(self._show(sample, codec, data))

    def _show(self, sample: Sample, codec: str, data: bytes) -> Sample:
        decoder = self._decoder(sample.topic, codec)
        if decoder is None:
            return sample
        image = decoder.decode(data, sample.wire_seq)
        if image is not None:
            return replace(sample, shown_ns=time.time_ns())
        if decoder.waiting_for_keyframe:
            now = time.monotonic()
            if now - self._last_request.get(sample.topic, -1e9) >= REQUEST_INTERVAL_S:
                self._last_request[sample.topic] = now
                self._request(sample.topic)
        return sample

    def _decoder(self, topic: str, codec: str) -> Any:
        decoder = self._decoders.get(topic)
        if decoder is None or decoder.codec != codec:
            decoder = self._make(codec)
            if decoder is None:
                if codec not in self.unavailable:
                    self.unavailable.add(codec)
                    print(f"e2e consumer: no {codec} decoder here (PyAV missing?): video "
                          "frames are recorded but not decoded", file=sys.stderr)
                return None
            self._decoders[topic] = decoder
        return decoder


def _pyav_decoder(codec: str) -> Any:
    try:
        from fleetctl.client.video import VideoDecoder, VideoError

        return VideoDecoder(codec)
    except (ImportError, VideoError):
        return None
