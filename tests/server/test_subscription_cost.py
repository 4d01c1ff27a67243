"""What a new subscription costs the relay beside full latched and video stores: a prefix
pattern only the stored topics in its range, a pattern that must look at every stored
topic a share of its connection's control request rate in proportion (no sockets)."""

from __future__ import annotations

import json
from typing import Any

import pytest

from fleetctl.server import firstframes
from fleetctl.server.admission import TokenBucket
from fleetctl.server.config import ServerConfig, ServerLimits
from fleetctl.server.latched import MAX_ENTRIES
from fleetctl.server.metrics import Metrics
from fleetctl.server.registry import RobotRegistry
from fleetctl.server.relay import Peer, RelayCore
from fleetctl.wire.control import decode_keyframe_request, encode_subscription
from tests.server.conftest import ALICE_TOKEN, BOB_TOKEN, auth_map, authed_peer
from tests.server.test_relay_keyframes import requests, video_frame
from tests.server.test_relay_latched import binaries, latched
from tests.support import ManualClock

STORED = MAX_ENTRIES  # a full latched store (4,096 topics)


def test_a_charge_goes_below_empty_and_the_refill_pays_it_back() -> None:
    now = [0.0]
    bucket = TokenBucket(20.0, 64, clock=lambda: now[0])
    bucket.charge(10)
    assert bucket.level() == 54
    bucket.charge(100)
    assert bucket.level() == -46 and not bucket.take()
    assert bucket.wait_s() == 47 / 20
    bucket.charge(1000)
    assert bucket.level() == -64  # at most one burst of debt
    now[0] += 65 / 20
    assert bucket.take() and not bucket.take()


def make_core() -> tuple[RelayCore, ManualClock]:
    clock = ManualClock(10.0)
    config = ServerConfig(limits=ServerLimits())
    return RelayCore(config, auth_map(), RobotRegistry(None, 5.0), Metrics(), clock), clock


def fill_latched(core: RelayCore) -> list[str]:
    """A full latched store: *STORED* topics, ``/husky1/r<i // 32>/t<i>``, sent by alice."""
    topics = [f"/husky1/r{i // 32}/t{i}" for i in range(STORED)]
    for topic in topics:
        core.latched.put(("alice",), topic, latched(topic, "m"), None)
    assert len(core.latched) == STORED
    return topics


def control_requests_left(core: RelayCore, p: Peer) -> int:
    """Subscribe/unsubscribe a topic nothing is stored on until the relay says
    ``rate_limited`` (the clock stands still): the control requests *p* had left."""
    spent = 0
    while True:
        core.on_binary(p, encode_subscription("/husky1/nothing", spent % 2 == 0))
        answers = [json.loads(f) for _, f in p.outbound.pop_batch(10**9) if isinstance(f, str)]
        if any(a.get("code") == "rate_limited" for a in answers):
            return spent
        spent += 1


def test_a_prefix_pattern_costs_one_request_and_finds_its_range_in_store_order() -> None:
    core, _clock = make_core()
    topics = fill_latched(core)
    bob = authed_peer(core, token=BOB_TOKEN)
    core.on_binary(bob, encode_subscription("/husky1/r7/.*"))
    assert [t for t, _ in binaries(bob)] == topics[224:256]
    burst = core.limits.max_subscriptions_per_connection
    assert control_requests_left(core, bob) == burst - 1


def test_a_pattern_that_looks_at_every_topic_is_charged_for_it() -> None:
    """``.*`` beside 4,096 latched topics: 4,096 looked at, 4,096 found and queued,
    2 x 4,096 / 256 = 32 control requests more than a literal."""
    core, _clock = make_core()
    fill_latched(core)
    alice = authed_peer(core, token=ALICE_TOKEN)
    core.on_binary(alice, encode_subscription(".*"))
    assert len(binaries(alice)) == STORED
    burst = core.limits.max_subscriptions_per_connection
    extra = 2 * STORED // firstframes.WORK_PER_CONTROL_REQUEST
    assert control_requests_left(core, alice) == burst - 1 - extra
    # The same token's other connections share the bill (one bucket per identity set).
    assert control_requests_left(core, authed_peer(core, token=ALICE_TOKEN)) == 0


def test_video_topics_are_indexed_and_charged_too() -> None:
    core, _clock = make_core()
    robot = authed_peer(core, "127.0.0.2")
    for i in range(512):
        core.on_binary(robot, video_frame(f"/husky1/cam{i // 32}/v{i}"))
    bob = authed_peer(core, token=BOB_TOKEN)
    core.on_binary(bob, encode_subscription("/husky1/cam3/.*"))
    assert requests(robot) == [f"/husky1/cam3/v{i}" for i in range(96, 128)]
    core.on_binary(bob, encode_subscription("/husky1/.*"))  # the 480 others
    assert len(requests(robot)) == 480
    burst = core.limits.max_subscriptions_per_connection
    extra = (512 + 512) // firstframes.WORK_PER_CONTROL_REQUEST  # (32 were asked, too)
    assert control_requests_left(core, bob) == burst - 2 - extra


def _churn(core: RelayCore, clock: ManualClock, p: Peer, pattern: str, seconds: float) -> int:
    """*p* toggles *pattern* as fast as the relay lets it for *seconds* of clock (the
    I/O layer's part played here: a throttled connection is read again once its bucket
    has a token); returns how many times it was subscribed."""
    subscribed = 0
    start = clock.now_s
    on = True
    while clock.now_s - start < seconds:
        core.on_binary(p, encode_subscription(pattern, on))
        for _, frame in p.outbound.pop_batch(10**9):
            if isinstance(frame, str):
                answer: dict[str, Any] = json.loads(frame)
                subscribed += answer["type"] == "subscribed"
                on = on != (answer["type"] in ("subscribed", "unsubscribed"))
        if p.throttled:
            clock.now_s += core._control_bucket(p).wait_s()
            p.throttled = False
        clock.now_s += 0.001  # a request takes the client at least a round trip
    return subscribed


def test_a_token_churning_a_pattern_over_a_full_store_scans_it_at_a_bounded_rate() -> None:
    """At 20 requests/s and 256 units of work each, ``.*`` over 4,096 latched topics
    (33 requests) is served ~0.6 times a second after the burst; a prefix pattern's churn
    is not slowed."""
    core, clock = make_core()
    fill_latched(core)
    alice = authed_peer(core, token=ALICE_TOKEN)
    rate = core.limits.max_control_requests_per_s
    burst = core.limits.max_subscriptions_per_connection
    scans = _churn(core, clock, alice, ".*", 60.0)
    per_scan = 2 + 2 * STORED // firstframes.WORK_PER_CONTROL_REQUEST  # (and its unsubscribe)
    assert scans <= (burst + rate * 60.0) / per_scan + 1
    assert scans >= (rate * 60.0) / per_scan - 1
    bob = authed_peer(core, token=BOB_TOKEN)
    assert _churn(core, clock, bob, "/husky1/r7/.*", 10.0) >= (burst + rate * 10.0) / 2 - 2


def test_video_topics_of_other_replicas_are_indexed_and_bounded(
        monkeypatch: pytest.MonkeyPatch) -> None:
    core, _clock = make_core()
    forwarded: list[str] = []

    def forward(frame: bytes) -> bool:
        forwarded.append(decode_keyframe_request(frame))
        return True

    monkeypatch.setattr(core.fanout, "forward_keyframe_request", forward)
    for i in range(firstframes.MAX_REMOTE_VIDEO_TOPICS + 1):  # the first is forgotten
        firstframes.on_remote_video_topic(core, f"/husky1/cam{i // 32}/v{i}")
    assert len(core.remote_video) == firstframes.MAX_REMOTE_VIDEO_TOPICS
    assert "/husky1/cam0/v0" not in core.remote_video
    forwarded.clear()
    bob = authed_peer(core, token=BOB_TOKEN)
    core.on_binary(bob, encode_subscription("/husky1/cam0/.*"))
    assert forwarded == [f"/husky1/cam0/v{i}" for i in range(1, 32)]


def test_a_resumed_session_asks_each_stored_topic_once(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A session holding 50 patterns RE2 cannot bound, resumed beside a full latched
    store: its patterns are asked together (one joined call per stored topic, not 50),
    and it gets each of its messages once, in the store's order."""
    from tests.server.test_subscriptions import _Calls

    core, clock = make_core()
    topics = fill_latched(core)
    tab = authed_peer(core, token=ALICE_TOKEN, session="tab")
    for k in range(50):
        clock.now_s += 100.0  # (each costs 17 control requests: refilled)
        core.on_binary(tab, encode_subscription(f".*/t{k}"))
    assert len(binaries(tab)) == 50
    core.close_peer(tab)
    clock.now_s += 100.0
    for topic in topics:
        tab.perms.may_receive(topic)  # (alice's receive rule answers, cached per topic)
    calls = _Calls(monkeypatch)
    again = authed_peer(core, token=ALICE_TOKEN, session="tab")
    assert [t for t, _ in binaries(again)] == topics[:50]
    assert calls.by == {"FullMatch": 0, "AnyOf": STORED}


def test_the_charge_is_the_work_or_the_loop_time_whichever_is_more() -> None:
    assert firstframes.extra_requests(255, 0.0) == 0
    assert firstframes.extra_requests(2 * 256, 0.0005) == 2
    assert firstframes.extra_requests(10, 0.0035) == 3  # a slow join: its time counts


def test_first_frames_that_take_loop_time_are_charged_by_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    core, clock = make_core()
    fill_latched(core)
    original = firstframes.on_new_subscriptions

    def slow(core: RelayCore, peer: Peer, patterns: list[str]) -> int:
        clock.now_s += 0.05  # as if they had taken 50 ms of the loop
        return original(core, peer, patterns)

    monkeypatch.setattr(firstframes, "on_new_subscriptions", slow)
    bob = authed_peer(core, token=BOB_TOKEN)
    core.on_binary(bob, encode_subscription("/husky1/r7/.*"))
    monkeypatch.undo()  # (the requests counted below take no time)
    assert len(binaries(bob)) == 32
    burst = core.limits.max_subscriptions_per_connection
    # Its own request, 50 more for the 50 ms, one refilled meanwhile (20/s).
    assert control_requests_left(core, bob) == burst - 1 - 50 + 1


def test_a_resume_while_the_identity_owes_first_frames_is_refused_until_paid() -> None:
    """Reconnecting is not a control request: a session of patterns RE2 cannot bound,
    resumed again and again beside a full store, would match them all each time. A
    resume while the identity set's bucket is below empty (the last first frames not
    paid for) is closed 4429 with the wait, and the session kept: once the refill has
    paid the debt, the same session resumes with its messages."""
    from tests.server.conftest import closes

    core, clock = make_core()
    topics = fill_latched(core)
    tab = authed_peer(core, token=ALICE_TOKEN, session="tab")
    for k in range(8):
        clock.now_s += 100.0
        core.on_binary(tab, encode_subscription(f".*/t{k}"))
    core.close_peer(tab)
    clock.now_s += 100.0
    bucket = core._control_bucket(tab)
    while bucket.take():  # the identity's other requests spent the bucket: no debt yet
        pass
    again = authed_peer(core, token=ALICE_TOKEN, session="tab")
    assert [t for t, _ in binaries(again)] == topics[:8] and not closes(again)
    core.close_peer(again)
    assert bucket.level() < 0  # the resume's first frames: charged, not yet paid back
    refused = authed_peer(core, token=ALICE_TOKEN, session="tab")
    (code, reason), = closes(refused)
    assert code == 4429 and "resume" in reason and "retry in" in reason
    assert binaries(refused) == []
    clock.now_s += bucket.wait_s() + 1.0
    later = authed_peer(core, token=ALICE_TOKEN, session="tab")
    assert [t for t, _ in binaries(later)] == topics[:8] and not closes(later)


def test_a_resume_with_an_empty_bucket_but_no_debt_is_served() -> None:
    """A burst of plain subscribes empties the bucket without debt: a resume then is a
    robot back from a cut, not a loop, and is served."""
    from tests.server.conftest import closes

    core, _clock = make_core()
    robot = authed_peer(core, token=ALICE_TOKEN, session="s")
    core.on_binary(robot, encode_subscription("/husky1/cmd"))
    core.close_peer(robot)
    bucket = core._control_bucket(robot)
    while bucket.take():
        pass
    assert 0 <= bucket.level() < 1
    back = authed_peer(core, token=ALICE_TOKEN, session="s")
    assert not closes(back)
