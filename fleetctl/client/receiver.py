"""The receive half of the robot link: frames from the server to ``on_frame``.

Fragments are reassembled (``fleetctl.wire.fragments.Reassembler``: a message with a lost
fragment is dropped and counted, never delivered corrupt), then Compressed frames are
decompressed (``fleetctl.wire.compression``: bounded; a frame that fails is dropped,
counted and logged, never delivered); a no_drop frame that repeats one already delivered
is a resend after a reconnect and is dropped (at-least-once delivery made exactly-once).

Duplicates are recognised per sender, without a wire change: a resend is the same frame
again, so it carries the same ``(seq, publish_time_ns)``; another sender on the same topic
(a second operator, a reloaded page whose ``seq`` restarts at 1, a restarted robot client)
stamps its own publish times. So the receiver remembers, per topic, the
``(seq, publish_time_ns)`` of the last :data:`MAX_REMEMBERED_PER_TOPIC` no_drop frames
(at most ``dedupe_window``) and drops exactly those repeats. Two senders collide only if
they send the same ``seq`` in the same clock tick (a page stamps milliseconds).
"""

from __future__ import annotations

import logging
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from typing import Any

from fleetctl.wire.compression import COMPRESSED_TYPE, decompress
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import FRAGMENT_TYPE, Reassembler
from fleetctl.wire.metadata import read_metadata

logger = logging.getLogger("fleetctl.client.link")
_LOG_EVERY = 1000  # a misbehaving sender must not flood the log: first, then every 1000th
# Why 4096: resends after a reconnect are what was in flight (the server's socket buffers,
# a sender's un-ponged frames); far fewer no_drop frames than that per topic.
MAX_REMEMBERED_PER_TOPIC = 4096
# Why: topics come from the server; a flood of new no_drop topics evicts the oldest.
MAX_DEDUPE_TOPICS = 1024


class _Seen:
    """The ``(seq, publish_time_ns)`` of a topic's recent no_drop frames, bounded."""

    __slots__ = ("keys", "order")

    def __init__(self) -> None:
        self.keys: set[tuple[int, int]] = set()
        self.order: deque[tuple[int, int]] = deque()

    def add(self, key: tuple[int, int], limit: int) -> bool:
        """Remember *key*; return ``False`` if it was already remembered."""
        if key in self.keys:
            return False
        self.keys.add(key)
        self.order.append(key)
        while len(self.order) > limit:
            self.keys.discard(self.order.popleft())
        return True


class Receiver:
    """Reassembly, duplicate suppression and delivery of frames from the server.

    Args:
        clock: Monotonic clock in seconds (reassembly timeouts).
        on_frame: Gets every complete frame; its exceptions are logged and counted.
        reassembly_max_bytes: Bytes of incomplete fragmented messages kept.
        reassembly_timeout_s: An incomplete fragmented message is dropped after this.
        dedupe_window: How many recent no_drop frames per topic are remembered to
            recognise resends (capped at :data:`MAX_REMEMBERED_PER_TOPIC`).
        max_decompressed_bytes: Largest frame a Compressed frame may expand to; None means
            ``reassembly_max_bytes`` (the largest frame reassembly can produce).
    """

    def __init__(self, clock: Callable[[], float], on_frame: Callable[[bytes], None], *,
                 reassembly_max_bytes: int, reassembly_timeout_s: float,
                 dedupe_window: int, max_decompressed_bytes: int | None = None) -> None:
        self._clock = clock
        self._on_frame = on_frame
        self._dedupe_window = max(1, min(dedupe_window, MAX_REMEMBERED_PER_TOPIC))
        self._reassembler = Reassembler(reassembly_max_bytes, reassembly_timeout_s)
        self._max_decompressed_bytes = max_decompressed_bytes or reassembly_max_bytes
        self._seen: OrderedDict[str, _Seen] = OrderedDict()
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
        if meta.no_drop and self._is_duplicate(meta.topic, meta.seq, meta.publish_time_ns):
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

    def _is_duplicate(self, topic: str, seq: int, publish_time_ns: int) -> bool:
        seen = self._seen.get(topic)
        if seen is None:
            seen = self._seen[topic] = _Seen()
            if len(self._seen) > MAX_DEDUPE_TOPICS:
                self._seen.popitem(last=False)
        else:
            self._seen.move_to_end(topic)
        return not seen.add((seq, publish_time_ns), self._dedupe_window)

    def on_disconnect(self) -> None:
        """Keep what was seen (duplicates come right after a reconnect)."""

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
