"""How much of a large message each fragment carries on a slow link: whole TCP segments.

Why: on a link of a few Mbit/s the robot deflates every message
(:mod:`fleetctl.client.slowdeflate`), so a fragment's ~170 bytes of metadata shrink to a
back-reference, and what is left of the overhead is per packet: WireGuard, UDP, IP and
TCP take ~130 bytes of every segment. The scheduler sized fragments as a power of two of
their frame bytes (1 KiB there), so each deflated fragment left as one segment two
thirds full, and a camera's 100 KB images cost 1.23 bytes on the uplink per byte of
image against zenoh's 1.11 (docs/peers.md, "Large messages"). Pound sized its fragments
to the radio's MTU for the same reason; on TCP the unit is the segment: the send MSS.

So while deflating everything the robot gives each fragment the share of the message
that, deflated, fills whole segments: ``k`` segments of ``mss`` bytes, ``k`` the number
that fit in the fragment's link-time budget (at least one: a fragment that does not fill
its segment saves no link time for an urgent message, only bytes), less the WebSocket
header, room for the ack point written after it and what deflate adds around the payload,
divided by how far the payload deflates. Both are read off the topic's last fragments
deflated (:class:`SegmentFill`), near their worst (the 90th percentile), so that a middle
fragment does not spill a few bytes into a second, nearly empty segment. Not the worst:
a message's first fragment has a layout of its own (no index in its table) and its
second refers back to it, so their metadata is a poorer back-reference, 30-120 bytes
where a middle fragment's is ~15; sized for them, every middle fragment of a camera's
image would leave ~100 bytes of its segment empty (7 %), while sized for the middle ones
the first two may spill into one more packet each per message (~130 bytes over
WireGuard, 0.1-0.3 % of a 100 KB image).
"""

from __future__ import annotations

from collections import OrderedDict, deque
from typing import TypeVar

_N = TypeVar("_N", int, float)

# A client's WebSocket header for a payload of 126 to 65535 bytes: 2 bytes, a 16-bit
# length and the 4-byte mask.
WS_CLIENT_HEADER_BYTES = 8
# The ack point the link writes after a batch (fleetctl.client.transport): a ping with an
# 8-byte token, 14 bytes with its header and mask, in the same write. With the window
# holding two fragments it follows every second one; without room for it, it took a
# packet of its own (~146 bytes over WireGuard): in the e2e peer-large, 1.19 uplink bytes
# per image byte against 1.17-1.185 with the room.
ACK_POINT_BYTES = 14
# Before any fragment was deflated: what a fragment's metadata costs undeflated (~170
# bytes for common topics) with room for a long topic name.
DEFAULT_EXTRA_BYTES = 256
# The byte a block boundary may move between the parts (zlib's Z_BLOCK is not
# byte-aligned) and the spread of middle fragments around the quantile (6: metadata
# 13-21 bytes around a quantile of 15-16, payload ratios within 0.001 over 1.4 KB;
# measured on camera images and float32 clouds, tests/client/test_segmentfill.py). A
# stored block's 5-byte header is in the payload's ratio already.
SLACK_BYTES = 7
# A payload that deflates to almost nothing (a cloud of zeros) would ask for fragments of
# hundreds of KB: its raw share is capped at this many times the room in the segments.
MAX_RAW_PER_WIRE = 4.0
# Below this, filling segments is not worth a fragment layout of its own (a link whose
# MSS is tiny or a metadata estimate gone wrong): the scheduler's own size applies.
MIN_PAYLOAD_BYTES = 256
# How many recent fragments of a topic the estimates are taken over, at which quantile,
# and how many topics are remembered (least recently deflated forgotten first).
MEMORY_FRAGMENTS = 64
QUANTILE = 0.9
MAX_TOPICS = 64


class SegmentFill:
    """Per topic, what a deflated fragment costs beyond its payload and how far its
    payloads deflate, near their worst (:data:`QUANTILE`) over the topic's last
    :data:`MEMORY_FRAGMENTS` fragments; and the payload share that fills whole segments.

    Per topic because a camera's JPEG does not deflate and a lidar's cloud does: sized by
    one topic's figures, the other's fragments would spill into a second packet or leave
    their segment part empty. A topic with no fragment deflated yet is sized for
    undeflated metadata and an incompressible payload (its first message fills its
    segments less; none spills). Fed by :class:`fleetctl.linkdeflate.SmallMessageDeflate`
    (``fragment_observer``).
    """

    def __init__(self, memory: int = MEMORY_FRAGMENTS, max_topics: int = MAX_TOPICS) -> None:
        self._memory = memory
        self._max_topics = max_topics
        # topic -> (extra bytes, payload ratios) of its recent fragments
        self._topics: OrderedDict[str, tuple[deque[int], deque[float]]] = OrderedDict()

    def observe(self, topic: str, payload_in: int, payload_out: int, frame_out: int) -> None:
        """A fragment on *topic* whose *payload_in* payload bytes deflated to
        *payload_out*, the whole fragment to *frame_out* (its WebSocket payload)."""
        if payload_in <= 0:
            return
        seen = self._topics.get(topic)
        if seen is None:
            if len(self._topics) >= self._max_topics:
                self._topics.popitem(last=False)
            seen = self._topics[topic] = (deque(maxlen=self._memory),
                                          deque(maxlen=self._memory))
        else:
            self._topics.move_to_end(topic)
        seen[0].append(frame_out - payload_out)
        seen[1].append(payload_out / payload_in)

    def topics(self) -> list[str]:
        """The topics remembered, least recently deflated first."""
        return list(self._topics)

    def extra_bytes(self, topic: str) -> int:
        """What *topic*'s recent deflated fragments took beyond their payload, near the
        most (:data:`DEFAULT_EXTRA_BYTES` before any)."""
        seen = self._topics.get(topic)
        return DEFAULT_EXTRA_BYTES if seen is None else _near_worst(seen[0])

    def payload_ratio(self, topic: str) -> float:
        """*topic*'s recent deflated / raw payload ratios, near the worst (1.0 before
        any)."""
        seen = self._topics.get(topic)
        return 1.0 if seen is None else _near_worst(seen[1])

    def payload_bytes(self, topic: str, *, mss: int | None, budget_wire_bytes: float,
                      max_fragment_bytes: int) -> int | None:
        """The raw payload share per fragment of *topic* that fills whole segments of
        *mss* bytes once deflated, as many as fit in *budget_wire_bytes* (at least one),
        a fragment staying within *max_fragment_bytes* (the robot's configured bound; its
        metadata counted at :data:`DEFAULT_EXTRA_BYTES`). None when the MSS is unknown or
        either leaves too little room: the scheduler's own size then."""
        if mss is None or mss <= 0:
            return None
        segments = max(1, int(min(budget_wire_bytes, max_fragment_bytes) // mss))
        room = (segments * mss - WS_CLIENT_HEADER_BYTES - ACK_POINT_BYTES
                - self.extra_bytes(topic) - SLACK_BYTES)
        share = min(int(room / max(self.payload_ratio(topic), 1.0 / MAX_RAW_PER_WIRE)),
                    max_fragment_bytes - DEFAULT_EXTRA_BYTES)
        return share if min(room, share) >= MIN_PAYLOAD_BYTES else None


def _near_worst(values: deque[_N]) -> _N:
    """The :data:`QUANTILE` of *values* (never empty: a topic is remembered with one)."""
    ordered = sorted(values)
    return ordered[int(QUANTILE * (len(ordered) - 1))]
