"""Issue 14, item 2: one token toggling subscriptions cannot stall the relay."""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
import sqlite3
from collections.abc import Callable
from pathlib import Path

from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerConfig, ServerLimits
from fleetctl.server.metrics import Metrics
from fleetctl.server.permissions import PermissionsPool
from fleetctl.server.registry import RobotRegistry
from fleetctl.server.relay import Peer, RelayCore
from fleetctl.server.subscriptions import Refusal, SubscriptionMap
from fleetctl.wire.control import encode_subscription
from tests.server.conftest import (
    ALICE_TOKEN,
    BOB_TOKEN,
    auth_map,
    authed_peer,
    client,
    next_json,
)
from tests.support import ManualClock, string_frame


def make_core(clock: ManualClock, db: Path | None = None, **limits: float) -> RelayCore:
    config = ServerConfig(limits=ServerLimits(**limits))  # type: ignore[arg-type]
    return RelayCore(config, auth_map(), RobotRegistry(db, 5.0), Metrics(), clock=clock)


def codes(p: Peer) -> list[str]:
    import json
    return [json.loads(f)["code"] for _, f in p.outbound.pop_batch(10**9)
            if isinstance(f, str) and '"error"' in f]


def test_subscription_changes_are_rate_limited_per_identity() -> None:
    clock = ManualClock()
    core = make_core(clock, max_control_requests_per_s=10.0,
                     max_subscriptions_per_connection=64)
    pauses: list[float] = []
    a, b = authed_peer(core, token=ALICE_TOKEN), authed_peer(core, token=ALICE_TOKEN)
    b.throttle = pauses.append
    for i in range(64):  # the burst (a resubscribe after a reconnect) passes
        core.on_binary(a, encode_subscription(f"/t{i}", i % 2 == 0))
    assert codes(a) == []
    core.on_binary(b, encode_subscription("/x"))  # same identity: same bucket
    assert codes(b) == ["rate_limited"] and b.throttled and pauses == [0.1]
    for _ in range(100):  # discarded unread while throttled: no answer, no close
        core.on_binary(b, encode_subscription("/y"))
        core.on_text(b, '{"type": "list_robots"}')
    assert codes(b) == [] and not b.closing
    assert core.metrics.errors["rate_limited"] == 201
    bob = authed_peer(core, token=BOB_TOKEN)  # another identity is not affected
    core.on_binary(bob, encode_subscription("/husky1/x"))
    assert codes(bob) == []
    b.throttled = False  # what the I/O layer does after the pause
    clock.now_s += 0.5  # 5 more at 10/s
    for i in range(6):
        core.on_binary(b, encode_subscription(f"/u{i}"))
    assert codes(b) == ["rate_limited"]


def test_a_connection_whose_frames_are_held_gets_them_declined_not_discarded() -> None:
    """With *hold* (a fleetctl connection's I/O layer) a request over the rate, and every
    frame while throttled, is declined (offered again later), not discarded: nothing is
    counted as dropped and nothing answered until the pause ends."""
    clock = ManualClock()
    core = make_core(clock, max_control_requests_per_s=10.0,
                     max_subscriptions_per_connection=64)
    pauses: list[float] = []
    b = authed_peer(core, token=ALICE_TOKEN)
    b.throttle = pauses.append
    for i in range(64):
        assert core.on_binary(b, encode_subscription("/husky1/t", i % 2 == 0), hold=True)
    codes(b)
    over = encode_subscription("/husky1/x")
    assert not core.on_binary(b, over, hold=True)
    assert codes(b) == ["rate_limited"] and b.throttled and pauses == [0.1]
    assert not core.on_text(b, '{"type": "list_robots"}', hold=True)
    assert not core.on_binary(b, string_frame("/husky1/events", "e", no_drop=True), hold=True)
    assert codes(b) == [] and core.metrics.errors == {"rate_limited": 1}  # the error frame
    assert core.metrics.reads_paused == {"control_rate": 1}
    assert "/husky1/events" not in core.metrics.messages_in
    b.throttled = False  # what the I/O layer does after the pause
    clock.now_s += 0.2
    assert core.on_binary(b, over, hold=True)  # offered again: served
    assert "/husky1/x" in core.subs.patterns(b)


async def test_a_throttled_connection_is_paused_then_served_again(
    make_server: Callable[..., RelayServer],
) -> None:
    """Past its burst a connection is not read for a moment; what it sent waits and is
    served at the rate, in order, none of it discarded (a pong after a discarded frame
    would lose it: tests/server/test_pongs_after_rate_limits.py)."""
    # A burst of 64 answers: well inside the control FIFO (256), so none is itself dropped
    # as an overflow. 100/s: the 137 past the burst take ~1.4 s.
    limits = ServerLimits(max_subscriptions_per_connection=8, max_control_requests_per_s=100.0)
    async with make_server(limits=limits) as server, \
            client(server, token=ALICE_TOKEN) as ws:
        await next_json(ws, "welcome")
        loop = asyncio.get_running_loop()
        started = loop.time()
        for i in range(200):  # past the burst of 64
            await ws.send(encode_subscription(f"/husky1/t{i % 2}", i % 2 == 0))
        await ws.send(encode_subscription("/husky1/.*"))
        seen: list[dict[str, object]] = []
        while not seen or seen[-1].get("topic_regex") != "/husky1/.*":
            msg = await asyncio.wait_for(ws.recv(), 10.0)
            if isinstance(msg, str):
                seen.append(json.loads(msg))
        answers = [(a["type"], a["topic_regex"]) for a in seen if a["type"] != "error"]
        assert answers == [(("subscribed", "unsubscribed")[i % 2], f"/husky1/t{i % 2}")
                           for i in range(200)] + [("subscribed", "/husky1/.*")]
        assert "rate_limited" in [a.get("code") for a in seen]
        assert loop.time() - started >= 137 / 100.0  # served no faster than the rate
        assert server.metrics.closes.get(4429) is None
        assert server.metrics.reads_paused["control_rate"] >= 1


def test_pattern_bytes_are_capped_per_connection_and_per_identity() -> None:
    core = make_core(ManualClock(), max_pattern_bytes_per_connection=10_000,
                     max_pattern_bytes_per_identity=15_000)
    big = "/a/(" + "x|" * 1500 + "y)"  # ~3 KiB
    a, b = authed_peer(core, token=ALICE_TOKEN), authed_peer(core, token=ALICE_TOKEN)
    for i in range(4):
        core.on_binary(a, encode_subscription(big.replace("/a/", f"/a{i}/")))
    assert codes(a) == ["too_many_subscriptions"]  # the 4th would pass 10,000 bytes
    for i in range(3):
        core.on_binary(b, encode_subscription(big.replace("/a/", f"/b{i}/")))
    assert codes(b) == ["too_many_subscriptions"] * 2  # alice: at most 15,000 bytes in all
    assert core.subs.key_bytes("alice") <= 15_000
    core.close_peer(a)
    assert core.subs.key_bytes("alice") == core.subs.pattern_bytes(b)


def test_incremental_receiver_cache_matches_a_full_recompute() -> None:
    """Reference check: after any sequence of changes the cached answers equal what a
    fresh map with the same subscriptions computes."""
    rng = random.Random(14)
    perms = PermissionsPool().get(list(auth_map().identities[2:4]))  # alice + bob
    bob_only = PermissionsPool().get([auth_map().identities[3]])
    topics = [f"/husky{r}/{t}" for r in (1, 2) for t in ("scan", "goal_pose", "x")]
    patterns = ["/husky1/.*", "/husky2/.*", ".*/scan", "/husky1/scan", "/husky2/x", ".*"]
    live: SubscriptionMap[str] = SubscriptionMap(16)
    conns = {"c1": perms, "c2": bob_only, "c3": perms}
    for _ in range(400):
        for t in topics:
            live.receivers(t)  # keep the cache warm so every change updates it
        conn = rng.choice(list(conns))
        pattern = rng.choice(patterns)
        if rng.random() < 0.1:
            live.remove(conn)
        elif rng.random() < 0.5:
            with contextlib.suppress(Refusal):  # bob may not hold every literal
                live.subscribe(conn, conns[conn], pattern)
        else:
            live.unsubscribe(conn, pattern)
        fresh: SubscriptionMap[str] = SubscriptionMap(16)
        for c in conns:
            for p in live.patterns(c):
                fresh.subscribe(c, conns[c], p)
        for t in topics:
            assert set(live.receivers(t)) == set(fresh.receivers(t)), (t, conn, pattern)


def test_session_subscription_writes_are_batched_off_the_event_loop(tmp_path: Path) -> None:
    db = tmp_path / "fleet.db"
    core = make_core(ManualClock(), db)
    alice = authed_peer(core, token=ALICE_TOKEN, session="console")
    for i in range(50):
        core.on_binary(alice, encode_subscription("/husky1/x", i % 2 == 0))
    core.on_binary(alice, encode_subscription("/husky1/.*"))
    rows = sqlite3.connect(str(db)).execute("SELECT count(*) FROM sessions").fetchone()[0]
    assert rows == 0  # nothing committed on the relay's thread
    job = core.sessions.take_changes()
    assert job is not None and core.sessions.take_changes() is None  # one batch
    job()  # what the server runs in a worker thread
    stored = sqlite3.connect(str(db)).execute("SELECT patterns FROM sessions").fetchall()
    assert stored == [('["/husky1/.*"]',)]
