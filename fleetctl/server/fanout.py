"""Fan-out of accepted frames: the relay core's one seam for replicas (docs/scaling.md).

The core decides who may send and receive and what is dropped; a :class:`Fanout` only
carries an accepted frame to the subscribers that want it. :class:`LocalFanout` (the
default) delivers to this process's connections; the NATS fan-out
(:mod:`fleetctl.server.cluster.natsfanout`) does the same and also publishes to the other
replicas, and subscribes to the subjects :meth:`Fanout.follow` says local consumers want.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Protocol

from fleetctl.server.peer import Peer

if TYPE_CHECKING:
    from fleetctl.server.sessions import SessionTable
    from fleetctl.server.subscriptions import SubscriptionMap

MetricFamily = tuple[str, str, str, str, dict[str, float]]


class Fanout(Protocol):
    """Where accepted frames go."""

    def publish(self, topic: str, frame: bytes, no_drop: bool, message_id: int | None) -> None:
        """Deliver a frame accepted from a local sender to everyone who wants it."""

    def follow(self, pattern: str, delta: int, receive: tuple[str, ...] | None = None) -> None:
        """One more (``+1``) or one fewer (``-1``) local connection holds *pattern*; it
        may receive the topics of the *receive* regexes (``None``: not known)."""

    def forward_keyframe_request(self, frame: bytes) -> bool:
        """A keyframe request for a video topic whose publisher is not connected here:
        hand it to the other replicas. ``False``: there are none (one process)."""

    async def start(self) -> None:
        """Connect whatever carries frames between replicas (before the relay listens)."""

    async def stop(self) -> None:
        """Disconnect; frames not yet carried are dropped."""

    def metric_families(self) -> Iterable[MetricFamily]:
        """Counters and gauges for ``/metrics`` (see :meth:`Metrics.render`)."""


class LocalFanout:
    """Today's single-process delivery: each receiver's scheduler, then offline sessions.

    Args:
        subs: The subscription map (receivers with the receive rules applied).
        sessions: Named sessions (offline ones keep no_drop frames in their mailbox).
    """

    def __init__(self, subs: SubscriptionMap[Peer], sessions: SessionTable[Peer]) -> None:
        self.receivers = subs.receivers
        self.sessions = sessions

    def publish(self, topic: str, frame: bytes, no_drop: bool, message_id: int | None) -> None:
        if not no_drop:
            for receiver in self.receivers(topic):
                receiver.outbound.push(topic, frame, False, message_id)
            return
        for receiver in self.receivers(topic):
            feed = receiver.stream_feed  # a cluster's session: fed from the stream...
            if feed is None:
                receiver.outbound.push(topic, frame, True, message_id)
            elif feed.bypass() and receiver.outbound.push(topic, frame, True, message_id):
                feed.note_live()  # ...unless the stream is away: then live, as before
        if self.sessions.has_offline:
            self.sessions.deliver(topic, frame)

    def deliver_to_stream_fed(self, topic: str, frame: bytes, message_id: int | None) -> None:
        """A no_drop frame the connections fed from the sessions' stream skipped live
        will not be stored soon (the stream is away): give it to them live now, as
        :meth:`publish` does meanwhile."""
        for receiver in self.receivers(topic):
            feed = receiver.stream_feed
            if feed is not None and receiver.outbound.push(topic, frame, True, message_id):
                feed.note_live()

    def forward_keyframe_request(self, frame: bytes) -> bool:
        return False  # one process: a publisher not here is nowhere

    def follow(self, pattern: str, delta: int, receive: tuple[str, ...] | None = None) -> None:
        pass  # every frame is already here

    async def start(self) -> None:
        pass

    async def stop(self) -> None:
        pass

    def metric_families(self) -> Iterable[MetricFamily]:
        return ()
