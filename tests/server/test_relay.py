"""Unit tests of the relay core without sockets, and hypothesis fuzzing of frames."""

from __future__ import annotations

import json

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fleetctl.server.config import ServerConfig, ServerLimits
from fleetctl.server.metrics import Metrics
from fleetctl.server.registry import RobotRegistry
from fleetctl.server.relay import Peer, RelayCore
from fleetctl.wire import fragments
from fleetctl.wire.control import encode_subscription
from tests.server.conftest import ALICE_TOKEN, auth_map, authed_peer, closes
from tests.support import string_frame


def make_core(**limits: int) -> RelayCore:
    config = ServerConfig(no_drop_topics=("/.*/events",), limits=ServerLimits(**limits))
    return RelayCore(config, auth_map(), RobotRegistry(None, 5.0), Metrics())


def texts(p: Peer) -> list[dict[str, object]]:
    return [json.loads(f) for _, f in p.outbound.pop_batch(10**9) if isinstance(f, str)]


def test_forced_no_drop_topics_and_fragments_routed() -> None:
    core = make_core()
    robot, alice = authed_peer(core, "127.0.0.2"), authed_peer(core, token=ALICE_TOKEN)
    core.on_binary(alice, encode_subscription("/husky1/.*"))
    texts(alice)
    for i in range(3):  # config says /.*/events is no_drop: all three kept, in order
        core.on_binary(robot, string_frame("/husky1/events", str(i)))
    big = string_frame("/husky1/points", "p" * 5000)
    parts = fragments.split(big, topic="/husky1/points", message_id=9,
                            max_fragment_bytes=1024, no_drop=False)
    for part in parts:
        core.on_binary(robot, part)
    out = alice.outbound.pop_batch(10**9)
    assert [t for t, _ in out][:3] == ["/husky1/events"] * 3
    assert [f for _, f in out][3:] == parts  # every fragment of the latest message
    assert core.registry.names() == ["husky1"]


def test_token_frame_adds_identity_and_rewelcomes() -> None:
    core = make_core()
    robot = authed_peer(core, "127.0.0.2")
    assert texts(robot)[0]["identities"] == ["husky1"]
    core.on_text(robot, json.dumps({"token": ALICE_TOKEN}))
    assert texts(robot)[0]["identities"] == ["husky1", "alice"]
    assert robot.perms is not None and robot.perms.may_receive("/anything")


def test_close_peer_cleans_up() -> None:
    core = make_core()
    robot, alice = authed_peer(core, "127.0.0.2"), authed_peer(core, token=ALICE_TOKEN)
    core.on_binary(alice, encode_subscription(".*"))
    core.on_binary(robot, string_frame("/husky1/a"))
    core.close_peer(alice)
    core.close_peer(robot)
    assert core.subs.receivers("/husky1/a") == ()
    assert core.metrics.connections_open == 0 and not core.registry.online("husky1")


FRAME = string_frame("/husky1/scan", "payload")


@st.composite
def mutated(draw: st.DrawFn) -> bytes:
    base = bytearray(draw(st.sampled_from([FRAME, encode_subscription("/husky1/.*")])))
    for _ in range(draw(st.integers(1, 8))):
        pos = draw(st.integers(0, len(base) - 1))
        base[pos] = draw(st.integers(0, 255))
    cut = draw(st.integers(0, len(base)))
    return bytes(base[: cut if draw(st.booleans()) else len(base)])


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(frames=st.lists(st.one_of(st.binary(max_size=200), mutated()), min_size=1,
                       max_size=20))
def test_fuzzed_frames_never_crash_or_leak_to_others(frames: list[bytes]) -> None:
    core = make_core(max_malformed_in_row=1000)
    attacker, robot = authed_peer(core, token=ALICE_TOKEN), authed_peer(core, "127.0.0.2")
    watcher = authed_peer(core, token=ALICE_TOKEN)
    texts(attacker)
    core.on_binary(watcher, encode_subscription("/husky1/scan"))
    texts(watcher)
    for frame in frames:
        core.on_binary(attacker, frame)  # must not raise
    core.on_binary(robot, FRAME)
    delivered = [f for _, f in watcher.outbound.pop_batch(10**9) if isinstance(f, bytes)]
    assert delivered and delivered[-1] == FRAME  # the watcher is still served
    for msg in texts(attacker):
        assert msg["type"] in ("error", "subscribed", "unsubscribed")
    assert not closes(attacker)
