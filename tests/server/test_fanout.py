"""LocalFanout: connections fed from the sessions' stream get no_drop frames live only
while the stream is away, and the frames the stream did not take when it went away."""

from __future__ import annotations

from typing import Any

from fleetctl.server.fanout import LocalFanout


class Outbound:
    def __init__(self) -> None:
        self.pushed: list[tuple[str, bytes, bool]] = []

    def push(self, topic: str, frame: bytes, no_drop: bool, message_id: Any = None) -> bool:
        self.pushed.append((topic, frame, no_drop))
        return True


class Feed:
    def __init__(self) -> None:
        self.away = False
        self.live = 0

    def bypass(self) -> bool:
        return self.away

    def note_live(self) -> None:
        self.live += 1


class Receiver:
    def __init__(self, feed: Feed | None) -> None:
        self.stream_feed = feed
        self.outbound = Outbound()


class Subs:
    def __init__(self, receivers: list[Receiver]) -> None:
        self._receivers = receivers

    def receivers(self, topic: str) -> list[Receiver]:
        return self._receivers


class Sessions:
    has_offline = False


def test_stream_fed_connections_get_no_drop_frames_live_only_while_it_is_away() -> None:
    feed = Feed()
    plain, fed = Receiver(None), Receiver(feed)
    fanout = LocalFanout(Subs([plain, fed]), Sessions())  # type: ignore[arg-type]
    fanout.publish("/r/events", b"e1", True, None)
    fanout.publish("/r/pose", b"p1", False, None)
    assert plain.outbound.pushed == [("/r/events", b"e1", True), ("/r/pose", b"p1", False)]
    assert fed.outbound.pushed == [("/r/pose", b"p1", False)]  # e1 comes from the stream
    feed.away = True
    fanout.publish("/r/events", b"e2", True, None)
    assert fed.outbound.pushed[-1] == ("/r/events", b"e2", True) and feed.live == 1


def test_frames_the_stream_did_not_take_go_to_stream_fed_connections_only() -> None:
    feed = Feed()
    plain, fed = Receiver(None), Receiver(feed)
    fanout = LocalFanout(Subs([plain, fed]), Sessions())  # type: ignore[arg-type]
    fanout.deliver_to_stream_fed("/r/events", b"e1", None)
    assert fed.outbound.pushed == [("/r/events", b"e1", True)] and feed.live == 1
    assert plain.outbound.pushed == []  # it had the frame live already
