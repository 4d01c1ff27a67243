"""Integration: named sessions on a real relay (127.0.0.1:0) with real websockets clients."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from websockets.asyncio.client import ClientConnection

from fleetctl.server.app import RelayServer
from fleetctl.server.sessions import SESSION_HEADER, session_metric_id
from fleetctl.wire.metadata import read_metadata
from tests.server.conftest import ALICE_TOKEN, client, next_binary, next_json, subscribe, wait_for
from tests.server.test_app import closed_code, http_get
from tests.support import decode_text, string_frame

EVENTS = "/husky1/events"


def console(srv: RelayServer, name: str = "console") -> Any:
    """Alice's consumer, naming session *name* on the upgrade."""
    return client(srv, token=ALICE_TOKEN, additional_headers={SESSION_HEADER: name})


async def send_events(robot: ClientConnection, first: int, n: int, *, no_drop: bool = True,
                      topic: str = EVENTS) -> None:
    for i in range(first, first + n):
        await robot.send(string_frame(topic, f"e{i}", no_drop=no_drop, seq=i))


async def receive_texts(ws: ClientConnection, n: int) -> list[str]:
    return [decode_text(await next_binary(ws)) for _ in range(n)]


def mailbox_len(srv: RelayServer) -> int:
    return sum(len(s.mailbox) for s in srv.core.sessions)


def attached_and_acked(srv: RelayServer) -> bool:
    """The one session has a connection that acknowledged every no_drop frame sent."""
    (session,) = srv.core.sessions
    return session.attached is not None and session.attached.outbound.unacked_frames == 0


async def test_receiver_gets_what_it_missed_in_order_before_newer_frames(
        server: RelayServer) -> None:
    async with client(server, source="127.0.0.2") as robot:
        async with console(server) as receiver:
            assert (await subscribe(receiver, "/husky1/.*"))["type"] == "subscribed"
            await send_events(robot, 0, 1)
            assert await receive_texts(receiver, 1) == ["e0"]
            await wait_for(lambda: attached_and_acked(server))  # else e0 comes again
        await wait_for(lambda: server.core.sessions.offline_count == 1)
        await send_events(robot, 1, 50)
        await send_events(robot, 1000, 5, no_drop=False, topic="/husky1/scan")
        await wait_for(lambda: mailbox_len(server) == 50)
        async with console(server) as receiver:
            session = await next_json(receiver, "session")
            assert session["resumed"] and session["mailbox_frames"] == 50
            assert session["subscriptions"] == ["/husky1/.*"]
            await send_events(robot, 51, 10)  # newer: must come after the mailbox
            got = await receive_texts(receiver, 60)
            assert got == [f"e{i}" for i in range(1, 61)]
            # Resubscribing what the session reinstated is harmless.
            assert (await subscribe(receiver, "/husky1/.*"))["type"] == "subscribed"
            await send_events(robot, 61, 1)
            assert await receive_texts(receiver, 1) == ["e61"]
        status, metrics = await http_get(server.port, "/metrics")
        assert status == 200
        assert 'fleetctl_sessions{state="offline"} 1.0' in metrics
        label = session_metric_id((("alice",), "console"))
        assert f'fleetctl_session_mailbox_frames{{session="{label}"}} 0.0' in metrics
        assert "alice" not in metrics  # opaque labels: /metrics names nobody


async def test_server_restart_keeps_subscriptions_for_late_receivers(
        make_server: Callable[..., RelayServer]) -> None:
    async with make_server() as srv, console(srv) as receiver:
        assert (await subscribe(receiver, EVENTS))["type"] == "subscribed"
    # The server is gone and back, on the same database; the sender reconnects first.
    async with make_server() as again:
        assert again.core.sessions.offline_count == 1
        async with client(again, source="127.0.0.2") as robot:
            await send_events(robot, 0, 30)
            await wait_for(lambda: mailbox_len(again) == 30)
            async with console(again) as receiver:
                assert (await next_json(receiver, "session"))["mailbox_frames"] == 30
                await send_events(robot, 30, 5)
                assert await receive_texts(receiver, 35) == [f"e{i}" for i in range(35)]


async def test_droppable_frames_are_not_mailboxed(server: RelayServer) -> None:
    async with client(server, source="127.0.0.2") as robot:
        async with console(server) as receiver:
            assert (await subscribe(receiver, "/husky1/.*"))["type"] == "subscribed"
        await wait_for(lambda: server.core.sessions.offline_count == 1)
        await send_events(robot, 0, 20, no_drop=False, topic="/husky1/scan")
        await send_events(robot, 100, 1)
        await wait_for(lambda: mailbox_len(server) == 1)
        async with console(server) as receiver:
            assert (await next_json(receiver, "session"))["mailbox_frames"] == 1
            assert await receive_texts(receiver, 1) == ["e100"]
            await send_events(robot, 21, 1, no_drop=False, topic="/husky1/scan")
            frame = await next_binary(receiver)  # droppable data resumes fresh
            assert read_metadata(frame).topic == "/husky1/scan" and decode_text(frame) == "e21"


async def test_frames_written_to_a_dead_connection_are_delivered_again(
        server: RelayServer) -> None:
    async with client(server, source="127.0.0.2") as robot:
        receiver = await console(server)
        assert (await subscribe(receiver, EVENTS))["type"] == "subscribed"
        receiver.transport.pause_reading()  # a radio gone silent: nothing read, no pong
        await send_events(robot, 0, 40)
        (session,) = server.core.sessions
        peer = session.attached
        assert peer is not None
        await wait_for(lambda: peer.outbound.unacked_frames == 40)  # written, unacknowledged
        receiver.transport.abort()
        await wait_for(lambda: server.core.sessions.offline_count == 1)
        assert mailbox_len(server) == 40
        async with console(server) as again:
            assert await receive_texts(again, 40) == [f"e{i}" for i in range(40)]
            await wait_for(lambda: attached_and_acked(server))


async def test_takeover_and_bad_session_name_close_codes(server: RelayServer) -> None:
    async with console(server) as first:
        assert (await subscribe(first, EVENTS))["type"] == "subscribed"
        async with console(server) as second:
            assert await closed_code(first) == 4409
            assert (await next_json(second, "session"))["resumed"] is True
    async with console(server, "no spaces allowed") as bad:
        error = await next_json(bad, "error")
        assert error["code"] == "bad_session"
        assert await closed_code(bad) == 4400
    async with client(server, token=ALICE_TOKEN) as plain:  # no session: as before
        await next_json(plain, "welcome")
        assert (await subscribe(plain, EVENTS))["type"] == "subscribed"


async def test_a_resume_while_the_identity_owes_first_frames_is_closed_4429(
        server: RelayServer) -> None:
    """Through real sockets: a session resumed while alice's control requests are below
    empty (earlier first frames not paid for; charged here directly, as the relay does
    after a costly resume) gets an error frame and close 4429 with the wait, and keeps
    its session: once the debt is paid, the same session resumes."""
    async with console(server) as receiver:
        assert (await subscribe(receiver, EVENTS))["type"] == "subscribed"
    await wait_for(lambda: server.core.sessions.offline_count == 1)
    (bucket,) = server.core._buckets.values()
    bucket.charge(bucket.burst * 2)  # at most one burst of debt: 256 requests, ~13 s
    async with console(server) as refused:
        error = await next_json(refused, "error")
        assert error["code"] == "resume_throttled" and "retry in" in error["message"]
        assert await closed_code(refused) == 4429
        assert refused.close_reason is not None and "retry in" in refused.close_reason
    assert server.core.sessions.offline_count == 1  # kept for a later attach
    bucket.charge(-bucket.burst * 2)  # (paid back: the refill, without waiting 13 s)
    async with console(server) as receiver:
        session = await next_json(receiver, "session")
        assert session["resumed"] and session["subscriptions"] == [EVENTS]
