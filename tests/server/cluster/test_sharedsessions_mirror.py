"""The replica's mirror of the session records, without NATS: what a watch entry does to
it (hostile ones included), expiry, counting, and a held session written by another
replica (taken over)."""

from __future__ import annotations

import datetime
from typing import Any

from fleetctl.server.cluster.config import ClusterConfig
from fleetctl.server.cluster.framequeue import Queued
from fleetctl.server.cluster.sessionrecord import SessionRecord, encode_record, record_key
from fleetctl.server.cluster.sharedsessions import SharedSessions
from fleetctl.server.outbound import OutboundScheduler
from tests.support import ManualClock

KEY = (("alice",), "console")
OTHER = (("alice",), "laptop")


def sessions(clock: ManualClock) -> SharedSessions:
    return SharedSessions(ClusterConfig(name="relay-a", nats_urls=("nats://h:4222",)), 3600.0,
                          clock=clock)


def entry(shared: SharedSessions, key: tuple[tuple[str, ...], str], record: SessionRecord,
          revision: int, at_s: float) -> None:
    shared.on_entry(record_key(key), encode_record(record), None, revision,
                    datetime.datetime.fromtimestamp(at_s, datetime.UTC))


def test_entries_are_mirrored_counted_and_expire() -> None:
    clock = ManualClock(1_000_000.0)
    shared = sessions(clock)
    record = SessionRecord(("/husky1/.*",), 7, clock.now_s - 10, None)
    entry(shared, KEY, record, 1, clock.now_s)
    entry(shared, OTHER, record, 2, clock.now_s - 3000)
    assert shared.lookup(KEY) == record and shared.count(("alice",)) == 2
    clock.now_s += 700  # OTHER is past the expiry now, KEY is not
    assert shared.count(("alice",)) == 1 and shared.lookup(OTHER) is None
    shared.on_entry(record_key(KEY), None, "DEL", 3, None)
    assert shared.lookup(KEY) is None and shared.count(("alice",)) == 0


def test_hostile_entries_are_counted_not_kept() -> None:
    clock = ManualClock(1_000_000.0)
    shared = sessions(clock)
    shared.on_entry("no-dot-key", b"{}", None, 1, None)
    shared.on_entry(record_key(KEY), b'{"v": 1, "patterns": 5}', None, 2, None)
    assert shared.counters["malformed"] == 2 and shared.lookup(KEY) is None


async def test_a_held_session_written_by_another_replica_is_taken_over() -> None:
    clock = ManualClock(1_000_000.0)
    shared = sessions(clock)
    taken: list[bool] = []
    outbound = OutboundScheduler(1 << 20, 100)
    outbound.track_acks()
    shared.attach(KEY, {"/husky1/.*": None}, outbound, lambda _: True, lambda: True,
                  lambda: taken.append(True))
    held = shared._held[KEY]
    assert shared.lookup(KEY) == SessionRecord(("/husky1/.*",), None, clock.now_s, "relay-a")
    held.fresh_attach = False  # as once its attach was written (revision 5)
    held.revision = 5
    entry(shared, KEY, SessionRecord(("/husky1/.*",), None, clock.now_s, "relay-a"), 5,
          clock.now_s)
    assert not taken  # our own write coming back
    entry(shared, KEY, SessionRecord(("/husky1/.*",), 3, clock.now_s, "relay-b"), 6, clock.now_s)
    assert taken == [True] and shared.counters["taken_over"] == 1
    assert shared.lookup(KEY) == SessionRecord(("/husky1/.*",), 3, clock.now_s, "relay-b")
    await shared.stop()


def test_a_sessions_consumer_reads_only_its_patterns_subjects() -> None:
    from fleetctl.server.cluster.sharedsessions import session_subjects

    assert session_subjects("f_nd", []) == ()
    assert session_subjects("f_nd", ["/husky1/goal_pose"]) == ("f_nd.husky1.goal_pose",)
    # A wider pattern covers a narrower one: no overlapping filters (each frame once).
    assert session_subjects("f_nd", ["/husky1/goal_pose", "/husky1/.*", "/husky2/cmd"]) == (
        "f_nd.husky1.>", "f_nd.husky2.cmd")
    assert session_subjects("f_nd", [".*", "/husky1/x"]) == ("f_nd.>",)
    assert session_subjects("f_nd", ["(unclosed"]) == ()  # a hostile record's pattern


async def test_frames_waiting_for_a_failing_stream_go_out_live_too() -> None:
    import asyncio

    shared = sessions(ManualClock(1_000_000.0))
    away: list[list[Queued]] = []
    shared.on_away = away.append

    from nats.aio.msg import Msg

    class DownStream:  # NATS whose stream has no leader (being re-elected): no responders
        def __init__(self) -> None:
            self.acks: Any = None

        def new_inbox(self) -> str:
            return "_INBOX.test"

        async def subscribe(self, subject: str, cb: Any) -> Any:
            self.acks = cb

            class Sub:
                async def unsubscribe(self) -> None:
                    pass

            return Sub()

        async def publish(self, subject: str, payload: bytes, reply: str,
                          headers: dict[str, str]) -> None:
            answer = Msg(self, subject=reply, data=b"", headers={"Status": "503"})  # type: ignore[arg-type]
            asyncio.get_running_loop().call_soon(
                lambda: asyncio.ensure_future(self.acks(answer)))

    shared._nc = DownStream()  # type: ignore[assignment]
    shared.offer("/husky1/events", b"e1")
    shared.offer("/husky1/events", b"e2")
    task = asyncio.create_task(shared._publish_loop())
    try:
        from tests.support import wait_until

        await wait_until(lambda: bool(away), 5.0)
    finally:
        task.cancel()
    assert [[(q.subject, q.frame, q.topic) for q in batch] for batch in away] == [
        [("fleetctl_nd.husky1.events", b"e1", "/husky1/events"),
         ("fleetctl_nd.husky1.events", b"e2", "/husky1/events")]]
    assert shared.stream_away() and shared.counters["store_failures"] >= 1
    from fleetctl.server.cluster.sharedsessions import live_subject

    assert live_subject(shared.config, "fleetctl_nd.husky1.events") == "fleetctl.husky1.events"


class Nats:
    """The one thing ``stream_away`` asks of nats-py's client."""

    is_connected = True


def on_a_connection() -> tuple[SharedSessions, list[list[Queued]], Nats]:
    """Sessions on a (stand-in) NATS connection, recording what goes out when the
    stream goes away."""
    shared = sessions(ManualClock(1_000_000.0))
    away: list[list[Queued]] = []
    shared.on_away = away.append
    nats = Nats()
    shared._nc = nats  # type: ignore[assignment]
    return shared, away, nats


def test_nats_lost_hands_the_waiting_frames_over_once_per_outage() -> None:
    shared, away, nats = on_a_connection()
    shared.offer("/husky1/events", b"e1")
    assert not shared.stream_away() and away == []
    nats.is_connected = False  # the next frame's delivery asks first
    assert shared.stream_away()
    assert [[q.frame for q in batch] for batch in away] == [[b"e1"]]
    shared.offer("/husky1/events", b"e2")  # delivered live as it came: not handed again
    assert shared.stream_away() and len(away) == 1
    nats.is_connected = True
    assert not shared.stream_away()
    nats.is_connected = False  # a second outage: what still waits goes out again
    assert shared.stream_away()
    assert [q.frame for q in away[1]] == [b"e1", b"e2"]


def test_frames_stored_lately_are_handed_over_too_in_order() -> None:
    """A reader on the NATS node that died may never have handed on a frame stored just
    before: it goes out again with those still waiting, before any later one."""
    shared, away, nats = on_a_connection()
    shared.offer("/husky1/events", b"e1")
    shared._queue.popleft()  # stored
    shared.offer("/husky1/events", b"e2")  # waiting
    nats.is_connected = False
    assert shared.stream_away()
    assert [[q.frame for q in batch] for batch in away] == [[b"e1", b"e2"]]
