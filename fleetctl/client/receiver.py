"""The receive half of the robot link: frames from the server to ``on_frame``.

Fragments are reassembled (``fleetctl.wire.fragments.Reassembler``: a message with a lost
fragment is dropped and counted, never delivered corrupt), then Compressed frames are
decompressed (``fleetctl.wire.compression``: bounded; a frame that fails is dropped,
counted and logged, never delivered); a no_drop frame whose ``seq``
is not above the last seen on its topic is a resend after a reconnect and is dropped
(at-least-once delivery made exactly-once for in-order streams), unless it lies more than
``dedupe_window`` below: that is a restarted sender counting from a new base.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from typing import Any

from fleetctl.wire.compression import COMPRESSED_TYPE, decompress
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import FRAGMENT_TYPE, Reassembler
from fleetctl.wire.metadata import read_metadata

logger = logging.getLogger("fleetctl.client.link")
_LOG_EVERY = 1000  # a misbehaving sender must not flood the log: first, then every 1000th


class Receiver:
    """Reassembly, duplicate suppression and delivery of frames from the server.

    Args:
        clock: Monotonic clock in seconds (reassembly timeouts).
        on_frame: Gets every complete frame; its exceptions are logged and counted.
        reassembly_max_bytes: Bytes of incomplete fragmented messages kept.
        reassembly_timeout_s: An incomplete fragmented message is dropped after this.
        dedupe_window: How far below the last seen seq a no_drop frame counts as a
            duplicate rather than a restarted sender.
        max_decompressed_bytes: Largest frame a Compressed frame may expand to; None means
            ``reassembly_max_bytes`` (the largest frame reassembly can produce).
    """

    def __init__(self, clock: Callable[[], float], on_frame: Callable[[bytes], None], *,
                 reassembly_max_bytes: int, reassembly_timeout_s: float,
                 dedupe_window: int, max_decompressed_bytes: int | None = None) -> None:
        self._clock = clock
        self._on_frame = on_frame
        self._dedupe_window = dedupe_window
        self._reassembler = Reassembler(reassembly_max_bytes, reassembly_timeout_s)
        self._max_decompressed_bytes = max_decompressed_bytes or reassembly_max_bytes
        self._last_seq: dict[str, int] = {}
        self._counters: Counter[str] = Counter()
        self._decompression: Counter[str] = Counter()

    def on_binary(self, frame: bytes) -> None:
        """Take one binary frame from the server."""
        try:
            meta = read_metadata(frame)
            if meta.type == FRAGMENT_TYPE:
                whole = self._reassembler.feed(frame, self._clock())
                if whole is None:
                    return
                frame, meta = whole, read_metadata(whole)
        except WireError as exc:
            self._counters["malformed"] += 1
            logger.warning("dropped a malformed frame from the server: %s", exc)
            return
        if meta.type == COMPRESSED_TYPE:
            inflated = self._decompress(frame)
            if inflated is None:
                return
            frame, meta = inflated, read_metadata(inflated)  # checked by decompress
        if meta.no_drop and self._is_duplicate(meta.topic, meta.seq):
            self._counters["duplicates"] += 1
            return
        self._counters["frames"] += 1
        try:
            self._on_frame(frame)
        except Exception:
            self._counters["callback_errors"] += 1
            logger.exception("on_frame failed for a frame on %s", meta.topic)

    def _decompress(self, frame: bytes) -> bytes | None:
        """The original frame, or None when it cannot be had (counted, logged)."""
        try:
            inflated = decompress(frame, self._max_decompressed_bytes)
        except WireError as exc:
            self._decompression["failed"] += 1
            failed = self._decompression["failed"]
            if failed % _LOG_EVERY == 1:
                logger.warning("dropped a compressed frame (%d so far): %s", failed, exc)
            return None
        self._decompression["decompressed"] += 1
        self._decompression["compressed_bytes"] += len(frame)
        self._decompression["decompressed_bytes"] += len(inflated)
        return inflated

    def _is_duplicate(self, topic: str, seq: int) -> bool:
        last = self._last_seq.get(topic)
        if last is not None and last - self._dedupe_window < seq <= last:
            return True
        self._last_seq[topic] = seq
        return False

    def on_disconnect(self) -> None:
        """Keep seqs (duplicates come right after a reconnect); nothing else to reset."""

    def stats(self) -> dict[str, Any]:
        """Counters: frames, duplicates, malformed, callback_errors, reassembly, and
        decompression (decompressed, failed, compressed_bytes, decompressed_bytes)."""
        out: dict[str, Any] = dict(self._counters)
        out["reassembly"] = _reassembler_stats(self._reassembler)
        out["decompression"] = {key: self._decompression[key] for key in (
            "decompressed", "failed", "compressed_bytes", "decompressed_bytes")}
        return out


def _reassembler_stats(reassembler: Reassembler) -> dict[str, Any]:
    counters = dict(vars(reassembler.stats))
    counters["pending_bytes"] = reassembler.pending_bytes
    return counters
