"""Other replicas' no_drop frames are read from the stream only on the subjects local
interest covers, on real relay replicas and a real NATS cluster: a replica nobody asked
gets none of them, a new subscriber gets no history, and a change of interest under a
steady stream of events loses none and repeats none."""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Callable

import pytest
from nats.js.api import ConsumerInfo
from websockets.asyncio.client import ClientConnection

from fleetctl.server.app import RelayServer
from fleetctl.server.cluster import remotefeed
from fleetctl.server.cluster.natsfanout import NatsFanout
from fleetctl.server.cluster.remotefeed import MAX_FILTER_SUBJECTS, RemoteFeed
from fleetctl.server.cluster.sharedsessions import SharedSessions
from fleetctl.wire.metadata import read_metadata
from tests.server.cluster.conftest import stream_takes_stores
from tests.server.cluster.natsproc import NatsServer
from tests.server.conftest import ALICE_TOKEN, client, next_binary, next_json, subscribe
from tests.support import decode_text, string_frame, wait_until

EVENTS = "/husky1/events"


def shared(srv: RelayServer) -> SharedSessions:
    found = srv.core.sessions.shared
    assert found is not None
    return found


async def texts_on(ws: ClientConnection, topic: str, n: int) -> list[str]:
    out: list[str] = []
    while len(out) < n:
        frame = await next_binary(ws, 15.0)
        if read_metadata(frame).topic == topic:
            out.append(decode_text(frame))
    return out


async def reader_info(srv: RelayServer) -> ConsumerInfo:
    """What JetStream says of this replica's consumer of the stream."""
    remote = shared(srv)._remote
    assert remote is not None and remote._reader is not None
    sub = remote._reader.sub
    assert sub is not None
    return await sub.consumer_info()


async def delivered_to(srv: RelayServer) -> int:
    """Messages the NATS server sent this replica's reader of the stream."""
    info = await reader_info(srv)
    assert info.delivered is not None
    return info.delivered.consumer_seq or 0


def test_stream_subjects_follow_the_live_subjects_under_the_streams_root() -> None:
    feed = RemoteFeed("s", "fleet", "fleet_nd", "r1", "H", lambda *_: None, {},
                      lambda digest: True)
    assert feed.stream_subjects({"fleet.husky1.>", "fleet.husky2.events"}) == (
        "fleet_nd.husky1.>", "fleet_nd.husky2.events")
    assert feed.stream_subjects({"fleet.>"}) == ("fleet_nd.>",)
    assert feed.stream_subjects({"other.x"}) == ()  # not this fleet's
    many = {f"fleet.r{i}.events" for i in range(MAX_FILTER_SUBJECTS + 1)}
    assert feed.stream_subjects(many) == ("fleet_nd.>",)


@pytest.mark.slow
async def test_a_replica_reads_only_what_its_subscribers_asked_for(
        replicas: tuple[RelayServer, ...]) -> None:
    a, b = replicas
    async with client(a, source="127.0.0.2") as robot, \
            client(a, token=ALICE_TOKEN) as local, client(b, token=ALICE_TOKEN) as remote:
        await next_json(robot, "welcome")
        assert (await subscribe(local, EVENTS))["type"] == "subscribed"
        assert (await subscribe(remote, "/husky2/.*"))["type"] == "subscribed"
        await wait_until(lambda: shared(b).remote_subjects == ("fleetctl_nd.husky2.>",),
                         10.0)
        stored = shared(a).counters["stored"]
        for i in range(30):
            await robot.send(string_frame(EVENTS, f"e{i}", no_drop=True, seq=i))
        assert await texts_on(local, EVENTS, 30) == [f"e{i}" for i in range(30)]
        await wait_until(lambda: shared(a).counters["stored"] - stored == 30, 10.0)
        # Stored, and not one of them was sent to B: it reads husky2's subjects only.
        assert await delivered_to(b) == 0
        assert shared(b).counters["remote"] == 0

        # A subscriber on B now: the events from here on, none of the stream's history.
        assert (await subscribe(remote, EVENTS))["type"] == "subscribed"
        await wait_until(lambda: "fleetctl_nd.husky1.events" in shared(b).remote_subjects,
                         10.0)
        for i in range(30, 35):
            await robot.send(string_frame(EVENTS, f"e{i}", no_drop=True, seq=i))
        assert await texts_on(remote, EVENTS, 5) == [f"e{i}" for i in range(30, 35)]
        assert shared(b).counters["remote"] == 5


@pytest.mark.slow
@pytest.mark.parametrize("late", [False, True], ids=["handed-over", "late"])
async def test_interest_changing_under_a_stream_of_events_loses_and_repeats_none(
        replicas: tuple[RelayServer, ...], late: bool, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Late: the old consumer is never waited for, so every change takes the way of a
    busy replica (start after what it handled, skip what nobody here followed)."""
    if late:
        monkeypatch.setattr(remotefeed, "HANDOFF_S", 0.0)
    a, b = replicas
    n = 600
    async with client(a, source="127.0.0.2") as robot, client(b, token=ALICE_TOKEN) as viewer:
        await next_json(robot, "welcome")
        assert (await subscribe(viewer, EVENTS))["type"] == "subscribed"
        await wait_until(lambda: shared(b).remote_subjects == ("fleetctl_nd.husky1.events",),
                         10.0)
        counters = shared(b).counters
        handoffs = counters["handoffs"]

        async def send_all() -> None:
            for i in range(n):
                await robot.send(string_frame(EVENTS, f"e{i}", no_drop=True, seq=i))
                if i % 20 == 0:
                    await asyncio.sleep(0.002)  # a steady stream, not one burst

        sending = asyncio.create_task(send_all())
        received = asyncio.create_task(texts_on(viewer, EVENTS, n))
        # Wider (one subject replaces the narrow one), back to narrow, then another robot
        # added: three hand-overs while events flow.
        async with client(b, token=ALICE_TOKEN) as wide:
            assert (await subscribe(wide, "/husky1/.*"))["type"] == "subscribed"
            await wait_until(lambda: shared(b).remote_subjects == ("fleetctl_nd.husky1.>",),
                             10.0)
        await wait_until(lambda: shared(b).remote_subjects == ("fleetctl_nd.husky1.events",),
                         10.0)
        async with client(b, token=ALICE_TOKEN) as other:
            assert (await subscribe(other, "/husky2/events"))["type"] == "subscribed"
            await wait_until(lambda: len(shared(b).remote_subjects) == 2, 10.0)
        await sending
        assert await received == [f"e{i}" for i in range(n)]
        assert counters["handoffs"] - handoffs >= 3
        assert (counters["handoff_late"] > 0) == late
        assert counters["remote"] >= n


@pytest.mark.slow
async def test_a_replica_whose_reader_died_with_its_node_misses_no_event(
        make_replica: Callable[..., RelayServer], nats_cluster: list[NatsServer]) -> None:
    """The NATS node that hosts B's consumer of the stream is killed while a robot on A
    sends events: B says it cannot read the stream, A sends its recent events over core
    NATS again, and B's viewer gets every event, once, in order."""
    urls = [s.url for s in nats_cluster]
    a = make_replica("relay-a", urls)
    b = make_replica("relay-b", urls[1:] + urls[:1])
    n = 400
    async with a, b, client(a, source="127.0.0.2") as robot, \
            client(b, token=ALICE_TOKEN) as viewer:
        await next_json(robot, "welcome")
        await stream_takes_stores(a)
        assert (await subscribe(viewer, EVENTS))["type"] == "subscribed"
        await wait_until(lambda: shared(b).remote_subjects == ("fleetctl_nd.husky1.events",),
                         10.0)
        info = await reader_info(b)
        assert info.cluster is not None
        host = next(s for s in nats_cluster if s.name == info.cluster.leader)
        received = asyncio.create_task(texts_on(viewer, EVENTS, n))
        for i in range(n):
            await robot.send(string_frame(EVENTS, f"e{i}", no_drop=True, seq=i))
            if i == 100:
                host.stop()  # SIGKILL: B's consumer dies with it
            await asyncio.sleep(0.01)  # a robot's 100 Hz, not a synchronization
        got = await received
        # Every event, once, in order: also when the killed node held B's own connection
        # and the stream's leader, and A's core copies sent while B was reconnecting were
        # lost to B. They come again with A's replay, and B holds the later ones until
        # then (remoteorder.py).
        counters = shared(b).counters
        seen = {k: v for k, v in counters.items() if k.startswith(("order", "reader", "remote"))}
        assert got == [f"e{i}" for i in range(n)], (
            seen, [t for t in got if t not in {f"e{i}" for i in range(n)}],
            sorted(set(f"e{i}" for i in range(n)) - set(got), key=lambda t: int(t[1:])),
            [(x, y) for x, y in itertools.pairwise(got) if int(y[1:]) != int(x[1:]) + 1])
        assert counters["reader_away"] >= 1
        fan = a.core.fanout
        assert isinstance(fan, NatsFanout) and fan.replays >= 1
