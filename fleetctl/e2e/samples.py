"""The record a consumer writes per received message, and its JSON-lines form."""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass

from fleetctl.errors import FleetError


@dataclass(frozen=True)
class Sample:
    """One received message.

    Attributes:
        topic: Topic the message arrived on.
        seq: Sender's per-topic sequence number (metadata field 4).
        publish_time_ns: When the robot client got it from ROS (wall clock, ns since epoch).
        recv_time_ns: When the consumer had it whole (same host clock, ns since epoch).
        size_bytes: Frame size as received (bytes, after reassembly).
        consumer: Which consumer recorded it.
        wire_seq: Video only: the frame's metadata ``seq`` (the client numbers each topic's
            frames; a gap is a lost frame). ``seq`` is the source image's number.
        keyframe: Video only: the frame is a keyframe.
        shown_ns: Video only: when the consumer's decoder output the frame as a picture
            (wall clock, ns since epoch); None when it refused it (reference missing).
    """

    topic: str
    seq: int
    publish_time_ns: int
    recv_time_ns: int
    size_bytes: int
    consumer: str = "c0"
    wire_seq: int | None = None
    keyframe: bool | None = None
    shown_ns: int | None = None

    @property
    def is_video(self) -> bool:
        """A video frame (the video fields are set)."""
        return self.keyframe is not None

    @property
    def latency_ms(self) -> float:
        """Publish-to-receipt latency in milliseconds."""
        return (self.recv_time_ns - self.publish_time_ns) / 1e6


def dump(samples: Iterable[Sample]) -> str:
    """JSON lines, one sample per line."""
    return "".join(json.dumps({k: v for k, v in asdict(s).items() if v is not None},
                              separators=(",", ":")) + "\n" for s in samples)


def load(text: str, source: str = "<samples>") -> Iterator[Sample]:
    """Parse JSON lines written by :func:`dump`.

    Raises:
        FleetError: a line is not a sample (names *source* and the line number).
    """
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            yield Sample(**json.loads(line))
        except (TypeError, ValueError) as exc:
            raise FleetError(f"{source}:{lineno}: not a sample ({exc})") from exc
