"""Named sessions shared by real relay replicas on a real NATS cluster: resumed on another
replica with what they missed, in order; a replica killed outright loses nothing; a
newer connection on another replica takes the session over."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from fleetctl.server.app import RelayServer
from fleetctl.server.cluster.sessionrecord import SessionRecord
from fleetctl.server.cluster.sharedsessions import SharedSessions
from fleetctl.server.sessions import SESSION_HEADER
from fleetctl.wire.metadata import read_metadata
from tests.server.cluster.natsproc import NatsServer, free_port
from tests.server.conftest import ALICE_TOKEN, AUTH, client, next_binary, next_json, subscribe
from tests.support import decode_text, string_frame, wait_until

pytestmark = pytest.mark.slow

EVENTS = "/husky1/events"
KEY = (("alice",), "console")


def console(srv: RelayServer | int) -> Any:
    """Alice's consumer on *srv* (a server or a port), naming session ``console``."""
    port = srv if isinstance(srv, int) else srv.port
    return connect(f"ws://127.0.0.1:{port}/", max_size=None, compression=None,
                   additional_headers={"Authorization": f"Bearer {ALICE_TOKEN}",
                                       SESSION_HEADER: "console"})


def shared(srv: RelayServer) -> SharedSessions:
    found = srv.core.sessions.shared
    assert found is not None
    return found


def record(srv: RelayServer) -> SessionRecord | None:
    return shared(srv).lookup(KEY)


async def send_events(robot: ClientConnection, first: int, n: int) -> None:
    for i in range(first, first + n):
        await robot.send(string_frame(EVENTS, f"e{i}", no_drop=True, seq=i))


async def event_texts(ws: ClientConnection, n: int, timeout_s: float = 15.0) -> list[str]:
    out: list[str] = []
    while len(out) < n:
        frame = await next_binary(ws, timeout_s)
        if read_metadata(frame).topic == EVENTS:
            out.append(decode_text(frame))
    return out


async def test_session_resumes_on_another_replica_with_what_it_missed(
        replicas: tuple[RelayServer, ...]) -> None:
    a, b = replicas
    async with client(b, source="127.0.0.2") as robot:
        await next_json(robot, "welcome")
        async with console(a) as viewer:
            assert not (await next_json(viewer, "session"))["resumed"]
            assert (await subscribe(viewer, EVENTS))["type"] == "subscribed"
            # The feed starts after the subscription reached the stream's consumer.
            await wait_until(lambda: (r := record(b)) is not None and r.owner == "relay-a"
                             and r.patterns == (EVENTS,), 10.0)
            await send_events(robot, 0, 5)
            assert await event_texts(viewer, 5) == [f"e{i}" for i in range(5)]
            await wait_until(lambda: (r := record(b)) is not None and r.cursor is not None
                             and r.cursor >= 5, 10.0)
        # Offline: B's mirror sees the record without owner, at the acknowledged cursor.
        await wait_until(lambda: (r := record(b)) is not None and r.owner is None, 10.0)
        await send_events(robot, 5, 50)
        async with console(b) as viewer:
            session = await next_json(viewer, "session")
            assert session["resumed"] and session["subscriptions"] == [EVENTS]
            got = await event_texts(viewer, 50)
            await send_events(robot, 55, 5)  # live ones come after the replay
            got += await event_texts(viewer, 5)
            assert got == [f"e{i}" for i in range(5, 60)]
        await wait_until(lambda: (r := record(a)) is not None and r.owner is None
                         and r.cursor is not None, 10.0)


async def test_a_newer_connection_on_another_replica_takes_the_session_over(
        replicas: tuple[RelayServer, ...]) -> None:
    a, b = replicas
    async with console(a) as old:
        assert (await subscribe(old, EVENTS))["type"] == "subscribed"
        await wait_until(lambda: (r := record(b)) is not None and r.owner == "relay-a"
                         and r.patterns == (EVENTS,), 10.0)
        async with console(b) as new:
            session = await next_json(new, "session")
            assert session["resumed"] and session["subscriptions"] == [EVENTS]
            with pytest.raises(ConnectionClosed) as closed:
                await asyncio.wait_for(_read_forever(old), 10.0)
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 4409
            await wait_until(lambda: (r := record(a)) is not None and r.owner == "relay-b",
                             10.0)
            assert shared(a).counters["taken_over"] == 1


async def test_an_ended_session_is_deleted_everywhere(
        replicas: tuple[RelayServer, ...]) -> None:
    a, b = replicas
    async with console(a) as viewer:
        assert (await subscribe(viewer, EVENTS))["type"] == "subscribed"
        await wait_until(lambda: record(b) is not None, 10.0)
        from fleetctl.wire.control import encode_subscription

        await viewer.send(encode_subscription(EVENTS, subscribe=False))
        await next_json(viewer, "unsubscribed")
    await wait_until(lambda: record(a) is None and record(b) is None, 10.0)


async def _read_forever(ws: ClientConnection) -> None:
    while True:
        await ws.recv()


# -- a replica killed outright ----------------------------------------------------------


@pytest.fixture
def replica_process(tmp_path: Path, nats_cluster: list[NatsServer]
                    ) -> Iterator[Callable[[], tuple[subprocess.Popen[bytes], int]]]:
    """Start ``fleetctl server`` with a cluster section as its own process (on NATS node
    0); returns the process and its port."""
    started: list[subprocess.Popen[bytes]] = []

    def start() -> tuple[subprocess.Popen[bytes], int]:
        (tmp_path / "auth.yaml").write_text(yaml.safe_dump(AUTH))
        port = free_port()
        (tmp_path / "relay-a.yaml").write_text(yaml.safe_dump({
            "auth_map": "auth.yaml", "listen_host": "127.0.0.1", "listen_port": port,
            "database": "relay-a.db",
            "cluster": {"name": "relay-a", "nats_urls": [nats_cluster[0].url]}}))
        proc = subprocess.Popen(
            [sys.executable, "-c", "from fleetctl.cli.main import main; raise SystemExit(main())",
             "server", "-c", str(tmp_path / "relay-a.yaml")],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
        started.append(proc)
        return proc, port

    yield start
    for proc in started:
        if proc.poll() is None:
            proc.kill()
        proc.wait(30)


async def _connect_when_up(port: int, deadline_s: float = 30.0) -> ClientConnection:
    loop = asyncio.get_running_loop()
    end = loop.time() + deadline_s
    while True:
        try:
            return await console(port)
        except OSError:
            if loop.time() > end:
                raise
            await asyncio.sleep(0.1)  # a retry pace while the process starts


async def test_a_replica_killed_outright_loses_none_of_its_sessions_frames(
        make_replica: Callable[..., RelayServer], nats_cluster: list[NatsServer],
        replica_process: Callable[[], tuple[subprocess.Popen[bytes], int]]) -> None:
    proc, port = replica_process()
    b = make_replica("relay-b", [nats_cluster[1].url])
    async with b, client(b, source="127.0.0.2") as robot:
        await next_json(robot, "welcome")
        viewer = await _connect_when_up(port)
        assert (await subscribe(viewer, EVENTS))["type"] == "subscribed"
        await wait_until(lambda: (r := record(b)) is not None and r.owner == "relay-a"
                         and r.patterns == (EVENTS,), 15.0)
        await send_events(robot, 0, 20)
        seen = await event_texts(viewer, 20)
        # Killed while the robot keeps sending: no clean close, no last write.
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
        await send_events(robot, 20, 30)
        async with console(b) as again:
            assert (await next_json(again, "session"))["resumed"]
            # What the dead replica had sent but not seen acknowledged comes again; a
            # client drops those by (topic, seq), as fleetctl's receiver does.
            while "e49" not in seen:
                text = (await event_texts(again, 1))[0]
                if text not in seen:
                    seen.append(text)
        assert seen == [f"e{i}" for i in range(50)]
        with pytest.raises(ConnectionClosed):
            await viewer.recv()


async def test_nats_lost_local_session_frames_go_on_and_the_rest_follows_once_back(
        make_replica: Callable[..., RelayServer], nats_server: NatsServer) -> None:
    a = make_replica("relay-a", [nats_server.url])
    async with a, client(a, source="127.0.0.2") as robot, console(a) as viewer:
        await next_json(robot, "welcome")
        assert (await subscribe(viewer, EVENTS))["type"] == "subscribed"
        await wait_until(lambda: (r := record(a)) is not None and r.owner == "relay-a", 10.0)
        await send_events(robot, 0, 3)
        seen = await event_texts(viewer, 3)

        nats_server.stop()
        await wait_until(shared(a).stream_away, 10.0)
        await send_events(robot, 3, 3)
        # Local delivery goes on, live; the frames stored in the last 2 s come once more
        # first (a reader on a dying NATS node may not have handed them on; the client
        # drops them as duplicates).
        while "e5" not in seen:
            text = (await event_texts(viewer, 1))[0]
            if text not in seen:
                seen.append(text)
        assert seen == [f"e{i}" for i in range(6)]

        nats_server.start()  # the same store: the stream and the records are back
        await wait_until(lambda: not shared(a).stream_away(), 20.0)
        await send_events(robot, 6, 3)
        # The frames held while NATS was away reach the stream and come once more (the
        # client drops them as duplicates); the new ones follow, in order, once each.
        while "e8" not in seen:
            text = (await event_texts(viewer, 1, 20.0))[0]
            if text not in seen:
                seen.append(text)
        assert seen == [f"e{i}" for i in range(9)]


async def test_a_pattern_added_later_widens_the_sessions_consumer(
        replicas: tuple[RelayServer, ...]) -> None:
    a, b = replicas
    other = "/husky1/alerts"
    async with client(b, source="127.0.0.2") as robot, console(a) as viewer:
        await next_json(robot, "welcome")
        assert (await subscribe(viewer, EVENTS))["type"] == "subscribed"
        await wait_until(lambda: (r := record(b)) is not None and r.patterns == (EVENTS,),
                         10.0)
        await robot.send(string_frame(other, "not yet", no_drop=True, seq=1))
        await send_events(robot, 0, 2)
        assert await event_texts(viewer, 2) == ["e0", "e1"]  # the alert was not asked for
        assert (await subscribe(viewer, other))["type"] == "subscribed"
        feed = shared(a)._held[KEY].feed
        assert feed is not None
        await wait_until(lambda: len(feed.subjects) == 2, 10.0)
        await robot.send(string_frame(other, "now", no_drop=True, seq=2))
        await send_events(robot, 2, 1)
        got = []
        while len(got) < 2:
            frame = await next_binary(viewer, 15.0)
            got.append((read_metadata(frame).topic, decode_text(frame)))
        assert got == [(other, "now"), (EVENTS, "e2")]
