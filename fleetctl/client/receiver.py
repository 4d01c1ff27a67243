"""The receive half of the robot link: frames from the server to ``on_frame``.

Fragments are reassembled (``fleetctl.wire.fragments.Reassembler``: a message with a lost
fragment is dropped and counted, never delivered corrupt); a no_drop frame whose ``seq``
is not above the last seen on its topic is a resend after a reconnect and is dropped
(at-least-once delivery made exactly-once for in-order streams), unless it lies more than
``dedupe_window`` below: that is a restarted sender counting from a new base.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from typing import Any

from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import FRAGMENT_TYPE, Reassembler
from fleetctl.wire.metadata import read_metadata

logger = logging.getLogger("fleetctl.client.link")


class Receiver:
    """Reassembly, duplicate suppression and delivery of frames from the server.

    Args:
        clock: Monotonic clock in seconds (reassembly timeouts).
        on_frame: Gets every complete frame; its exceptions are logged and counted.
        reassembly_max_bytes: Bytes of incomplete fragmented messages kept.
        reassembly_timeout_s: An incomplete fragmented message is dropped after this.
        dedupe_window: How far below the last seen seq a no_drop frame counts as a
            duplicate rather than a restarted sender.
    """

    def __init__(self, clock: Callable[[], float], on_frame: Callable[[bytes], None], *,
                 reassembly_max_bytes: int, reassembly_timeout_s: float,
                 dedupe_window: int) -> None:
        self._clock = clock
        self._on_frame = on_frame
        self._dedupe_window = dedupe_window
        self._reassembler = Reassembler(reassembly_max_bytes, reassembly_timeout_s)
        self._last_seq: dict[str, int] = {}
        self._counters: Counter[str] = Counter()

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
        if meta.no_drop and self._is_duplicate(meta.topic, meta.seq):
            self._counters["duplicates"] += 1
            return
        self._counters["frames"] += 1
        try:
            self._on_frame(frame)
        except Exception:
            self._counters["callback_errors"] += 1
            logger.exception("on_frame failed for a frame on %s", meta.topic)

    def _is_duplicate(self, topic: str, seq: int) -> bool:
        last = self._last_seq.get(topic)
        if last is not None and last - self._dedupe_window < seq <= last:
            return True
        self._last_seq[topic] = seq
        return False

    def on_disconnect(self) -> None:
        """Keep seqs (duplicates come right after a reconnect); nothing else to reset."""

    def stats(self) -> dict[str, Any]:
        """Counters: frames, duplicates, malformed, callback_errors, reassembly."""
        out: dict[str, Any] = dict(self._counters)
        out["reassembly"] = _reassembler_stats(self._reassembler)
        return out


def _reassembler_stats(reassembler: Reassembler) -> dict[str, Any]:
    counters = dict(vars(reassembler.stats))
    counters["pending_bytes"] = reassembler.pending_bytes
    return counters
