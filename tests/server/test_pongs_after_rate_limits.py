"""No pong after frames the relay's rate limits kept from it, on a connection it keeps open.

A pong tells a client that everything it sent before the ping was taken, and the robot's
link forgets its no_drop messages on it (docs/security.md, "A pong acknowledges only
frames the relay took"). Over the control request rate (``rate_limited``) the relay used
to discard, unparsed, every frame already read after the request that went over it, and
over the new-topic rate (``new_topic_rate``) it dropped frames on topics not routed yet;
the connection stayed open and the next ping was answered, so the client lost them for
good. Now such a frame and everything after it wait, the connection is not read meanwhile
(TCP pushes back on the client), and they are taken, in order, once the bucket has a
token again; the pong of a ping behind them goes only then.

Each test writes the burst, no_drop frames and a ping in one write through a real relay
and a hand-written client, and asserts that when the pong comes every frame before its
ping was taken (``messages_in``), in order.
"""

from __future__ import annotations

import asyncio
import itertools
import json
from collections.abc import Callable

import pytest

from fleetctl.server import relay
from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerLimits
from fleetctl.server.connection import READ_BYTES, THROTTLED_READ_BYTES
from fleetctl.wire.control import encode_subscription
from tests.security.conftest import RawClient
from tests.server.conftest import wait_for
from tests.server.test_pongs_after_discard import (
    BINARY,
    EVENTS,
    PING,
    PONG,
    TEXT,
    events,
    frame,
    opened,
    relay_side,
    taken,
    unread,
)
from tests.support import string_frame


async def pong_and_texts(raw: RawClient, last: bytes, srv: RelayServer, sent: int,
                         answers: int = 0, timeout_s: float = 20.0,
                         ) -> list[dict[str, object]]:
    """Read until the pong of the ping *last*, asserting that the relay had taken the
    *sent* frames on ``/husky1/events`` before it by then, and until *answers* answers
    (``subscribed``, ``unsubscribed``, ``robots``: they may come after the pong, which
    is written at once while the relay's writer sends queued text frames). Returns the
    JSON text frames."""
    texts: list[dict[str, object]] = []
    ponged = False

    def answered() -> int:
        return sum(t.get("type") in ("subscribed", "unsubscribed", "robots") for t in texts)

    async def scan() -> list[dict[str, object]]:
        nonlocal ponged
        while (got := await raw.next_frame()) is not None:
            if got[0] == PONG and got[1] == last:
                ponged = True
                assert taken(srv) == sent, (f"pong after {sent - taken(srv)} of {sent} "
                                            f"frames the relay did not take", texts[-3:])
            elif got[0] == TEXT:
                texts.append(json.loads(got[1]))
            if ponged and answered() >= answers:
                return texts
        raise AssertionError(f"closed before the pong and answers; texts: {texts[-3:]}")

    return await asyncio.wait_for(scan(), timeout_s)


# A burst of 64 control requests, then 100/s: the answers of a burst stay well inside the
# control FIFO (256), so none is itself dropped as an overflow.
LIMITS = ServerLimits(max_control_requests_per_s=100.0, max_subscriptions_per_connection=64)


def errors_of(texts: list[dict[str, object]]) -> list[object]:
    return [t.get("code") for t in texts if t.get("type") == "error"]


async def test_frames_after_a_control_request_over_the_rate_wait_for_it(
    make_server: Callable[..., RelayServer],
) -> None:
    """200 subscription changes (the burst is 64), then 5 no_drop frames and a ping, in
    one write: before, the 5 were discarded unparsed and the ping answered (0 of 5
    taken). Now every request is served, in order, at the rate, then the 5 frames, then
    the pong."""
    limits = LIMITS
    async with make_server(limits=limits) as srv:
        raw = await opened(srv)
        toggles = b"".join(frame(BINARY, encode_subscription("/husky1/x", n % 2 == 0))
                           for n in range(200))
        raw.writer.write(toggles + events(1, 5) + frame(PING, b"after"))
        texts = await pong_and_texts(raw, b"after", srv, 5, 200)  # e1..e5 taken
        assert "rate_limited" in errors_of(texts)  # told: it did go over the rate
        answers = [t["type"] for t in texts if t.get("type") in ("subscribed",
                                                                 "unsubscribed")]
        assert answers == ["subscribed", "unsubscribed"] * 100  # none lost, in order
        assert srv.metrics.reads_paused["control_rate"] >= 1
        assert not srv.metrics.closes
        raw.close()


async def test_frames_after_text_requests_over_the_rate_wait_for_them(
    make_server: Callable[..., RelayServer],
) -> None:
    """The same through websockets' recv() path (text frames: ``list_robots``): what
    follows the request over the rate waits behind it in websockets' bounded queue."""
    limits = LIMITS
    async with make_server(limits=limits) as srv:
        raw = await opened(srv)
        asks = frame(TEXT, b'{"type": "list_robots"}') * 200
        raw.writer.write(asks + events(1, 5) + frame(PING, b"after"))
        texts = await pong_and_texts(raw, b"after", srv, 5, 200)
        assert sum(t.get("type") == "robots" for t in texts) == 200
        assert "rate_limited" in errors_of(texts)
        raw.close()


async def test_frames_on_new_topics_over_the_rate_wait_for_it(
    make_server: Callable[..., RelayServer], monkeypatch: pytest.MonkeyPatch,
) -> None:
    """40 no_drop frames on new topics (the burst is 20 here) and a ping in one write:
    before, 20 were dropped (``new_topic_rate``) and the ping answered. Now the other 20
    wait for new-topic tokens, then the pong comes."""
    monkeypatch.setattr(relay, "NEW_TOPICS_BURST", 20)
    monkeypatch.setattr(relay, "NEW_TOPICS_PER_S", 50.0)
    async with make_server() as srv:
        raw = await opened(srv)
        frames = b"".join(frame(BINARY, string_frame(f"/husky1/t{n}", f"{n}", no_drop=True))
                          for n in range(40))
        raw.writer.write(frames + events(1, 2) + frame(PING, b"after"))
        texts = await pong_and_texts(raw, b"after", srv, 2)  # e1, e2 came after the 40
        got = sum(srv.metrics.messages_in.get(f"/husky1/t{n}", 0) for n in range(40))
        assert got == 40, texts
        assert errors_of(texts) == ["rate_limited"]  # told once
        assert srv.metrics.reads_paused["new_topic_rate"] >= 1
        assert "new_topic_rate" not in srv.metrics.errors  # nothing dropped
        raw.close()


async def test_what_waits_is_at_most_one_read_and_tcp_holds_the_rest(
    make_server: Callable[..., RelayServer],
) -> None:
    """A client flooding control requests: what the relay keeps for it is at most what
    one read brought; the rest stays in TCP (unread in the relay's socket, then in the
    client's buffer), and the relay serves the requests at the rate."""
    async with make_server(limits=LIMITS) as srv:
        raw = await opened(srv)
        [relay] = relay_side(srv, "alice")
        toggles = b"".join(frame(BINARY, encode_subscription("/husky1/x", n % 2 == 0))
                           for n in range(20_000))
        raw.writer.write(toggles)  # ~1.5 MB: far more than the socket buffers take
        most = 0

        def sampled() -> bool:
            nonlocal most
            most = max(most, relay.held_bytes)
            return srv.metrics.reads_paused.get("control_rate", 0) >= 4

        await wait_for(sampled, 20)
        assert 0 < most <= READ_BYTES  # not read again before what waits was taken
        assert unread(relay) > 0  # TCP pushes back on the client
        assert not srv.metrics.closes
        raw.close()


async def test_held_frames_are_offered_a_slice_per_loop_round(
    make_server: Callable[..., RelayServer],
) -> None:
    """When the pause ends, what waits is offered THROTTLED_READ_BYTES per event loop
    round, as a throttled connection's small reads were: the tokens an identity set saved
    during a pause are not spent in one round, with every other connection waiting."""
    async with make_server(limits=LIMITS) as srv:
        raw = await opened(srv)
        over = b"".join(frame(BINARY, encode_subscription("/husky1/x", n % 2 == 0))
                        for n in range(65))  # the 65th is over the burst
        raw.writer.write(over + events(1, 400) + frame(PING, b"after"))
        loop = asyncio.get_running_loop()
        rounds: list[int] = []  # frames taken, sampled once per loop round
        done = False

        def tick() -> None:
            rounds.append(taken(srv))
            if not done:
                loop.call_soon(tick)

        loop.call_soon(tick)
        try:
            await pong_and_texts(raw, b"after", srv, 400, answers=65)
        finally:
            done = True
        steps = [b - a for a, b in itertools.pairwise(rounds) if b > a]
        size = len(frame(BINARY, string_frame(EVENTS, "e100", no_drop=True, seq=100)))
        assert len(steps) > 1 and max(steps) <= THROTTLED_READ_BYTES // (size - 6) + 1, steps
        raw.close()
