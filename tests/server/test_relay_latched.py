"""The relay core with latched frames: kept per sender and topic, given first to new
subscribers that may receive them (no sockets)."""

from __future__ import annotations

import copy
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fleetctl.server.config import ServerConfig, ServerLimits
from fleetctl.server.metrics import Metrics
from fleetctl.server.registry import RobotRegistry
from fleetctl.server.relay import Peer, RelayCore
from fleetctl.wire.codec import default_codec
from fleetctl.wire.compression import COMPRESSED_TYPE, CompressionCodec, compress
from fleetctl.wire.control import encode_subscription
from fleetctl.wire.fragmenter import fast_split
from fleetctl.wire.fragments import Reassembler
from fleetctl.wire.metadata import read_metadata
from tests.server.conftest import AUTH, BOB_TOKEN, auth_map, authed_peer
from tests.support import string_frame

ALICE = "alice-secret-token"


def make_core(**limits: Any) -> RelayCore:
    config = ServerConfig(limits=ServerLimits(**limits))
    return RelayCore(config, auth_map(), RobotRegistry(None, 5.0), Metrics())


def latched(topic: str, text: str, *, no_drop: bool = False) -> bytes:
    codec = default_codec()
    cls = codec.registry.get("std_msgs/msg/String").cls
    return codec.encode(cls(text), "std_msgs/msg/String", topic, no_drop=no_drop, seq=1,
                        latched=True)


def binaries(p: Peer) -> list[tuple[str, bytes]]:
    return [(t, f) for t, f in p.outbound.pop_batch(10**9) if isinstance(f, bytes)]


def subscribe(core: RelayCore, p: Peer, pattern: str, on: bool = True) -> None:
    core.on_binary(p, encode_subscription(pattern, on))


def test_a_late_subscriber_gets_the_latched_message_before_live_data() -> None:
    core = make_core()
    robot = authed_peer(core, "127.0.0.2")
    core.on_binary(robot, latched("/husky1/map", "the map"))
    core.on_binary(robot, string_frame("/husky1/scan", "not latched: not kept"))
    core.close_peer(robot)  # the robot may be gone: the map stays
    alice = authed_peer(core, token=ALICE)
    subscribe(core, alice, "/husky1/.*")
    robot2 = authed_peer(core, "127.0.0.2")
    core.on_binary(robot2, string_frame("/husky1/scan", "live", no_drop=True))
    core.on_binary(robot2, string_frame("/husky1/map_updates", "live droppable"))
    out = binaries(alice)
    assert out[0] == ("/husky1/map", latched("/husky1/map", "the map"))
    assert [t for t, _ in out] == ["/husky1/map", "/husky1/scan", "/husky1/map_updates"]
    assert core.metrics.latched_delivered == 1


def test_acl_applies_as_for_live_data() -> None:
    core = make_core()
    alice = authed_peer(core, token=ALICE)
    core.on_binary(alice, latched("/husky1/goal_pose", "goal"))
    core.on_binary(alice, latched("/husky1/notes", "notes"))
    robot = authed_peer(core, "127.0.0.2")  # receives only goal_pose|initialpose
    subscribe(core, robot, ".*")
    assert [t for t, _ in binaries(robot)] == ["/husky1/goal_pose"]
    bob = authed_peer(core, token=BOB_TOKEN)  # receives /husky1/.*
    subscribe(core, bob, ".*")
    assert sorted(t for t, _ in binaries(bob)) == ["/husky1/goal_pose", "/husky1/notes"]


def test_resubscribing_gets_them_again_but_an_overlapping_pattern_does_not() -> None:
    core = make_core()
    robot, alice = authed_peer(core, "127.0.0.2"), authed_peer(core, token=ALICE)
    core.on_binary(robot, latched("/husky1/map", "m"))
    subscribe(core, alice, "/husky1/map")
    assert len(binaries(alice)) == 1
    subscribe(core, alice, "/husky1/map")  # the same subscription again: a no-op
    subscribe(core, alice, "/husky1/.*")  # already receives /husky1/map
    assert binaries(alice) == []
    subscribe(core, alice, "/husky1/map", on=False)
    subscribe(core, alice, "/husky1/.*", on=False)
    subscribe(core, alice, "/husky1/.*")
    assert [t for t, _ in binaries(alice)] == ["/husky1/map"]


def test_the_newest_message_of_each_sender_is_given() -> None:
    core = make_core()
    robot, alice = authed_peer(core, "127.0.0.2"), authed_peer(core, token=ALICE)
    core.on_binary(robot, latched("/husky1/map", "old"))
    core.on_binary(robot, latched("/husky1/map", "new"))
    core.on_binary(alice, latched("/husky1/map", "alice's"))
    bob = authed_peer(core, token=BOB_TOKEN)
    subscribe(core, bob, "/husky1/map")
    got = [f for _, f in binaries(bob)]
    assert got == [latched("/husky1/map", "new"), latched("/husky1/map", "alice's")]


def test_fragmented_and_compressed_latched_messages_are_given_whole() -> None:
    core = make_core()
    robot = authed_peer(core, "127.0.0.2")
    original = latched("/husky1/map", "cells " * 4000)
    packed = compress(original, codec=CompressionCodec.DEFLATE, topic="/husky1/map",
                      no_drop=False)
    assert read_metadata(packed).type == COMPRESSED_TYPE and read_metadata(packed).latched
    parts = fast_split(packed, topic="/husky1/map", message_id=3, max_fragment_bytes=300,
                       no_drop=False)
    assert len(parts) > 2
    for part in parts:
        core.on_binary(robot, part)
    big = latched("/husky1/description", "urdf " * 3000)
    desc_parts = fast_split(big, topic="/husky1/description", message_id=1,
                            max_fragment_bytes=1000, no_drop=False)
    for part in desc_parts[:-1]:  # incomplete: nothing kept yet
        core.on_binary(robot, part)
    alice = authed_peer(core, token=ALICE)
    subscribe(core, alice, "/husky1/.*")
    got = [f for _, f in binaries(alice)]
    assert got == parts
    reassembler = Reassembler(1 << 24, 10.0)
    assert [reassembler.feed(f, 0.0) for f in got][-1] == packed
    core.on_binary(robot, desc_parts[-1])  # completes live for alice, and in the store
    assert [f for _, f in binaries(alice)] == [desc_parts[-1]]
    bob = authed_peer(core, token=BOB_TOKEN)
    subscribe(core, bob, "/husky1/description")
    assert [f for _, f in binaries(bob)] == desc_parts


def test_byte_bound_evicts_and_metrics_show_it() -> None:
    frame_bytes = len(latched("/husky1/t0", "x" * 1000))
    core = make_core(latched_bytes=3 * frame_bytes)
    robot = authed_peer(core, "127.0.0.2")
    for i in range(5):
        core.on_binary(robot, latched(f"/husky1/t{i}", "x" * 1000))
    alice = authed_peer(core, token=ALICE)
    subscribe(core, alice, "/husky1/.*")
    assert sorted(t for t, _ in binaries(alice)) == ["/husky1/t2", "/husky1/t3", "/husky1/t4"]
    text = core.metrics.render()
    assert 'fleetctl_latched_events_total{event="evicted"} 2' in text
    assert f"fleetctl_latched_bytes {3 * frame_bytes}" in text
    assert "fleetctl_latched_messages 3" in text
    assert "fleetctl_latched_delivered_frames_total 3" in text


def test_latched_queue_bound_drops_a_message_whole() -> None:
    frame_bytes = len(latched("/husky1/t0", "x" * 1000))
    core = make_core(latched_bytes=2 * frame_bytes)
    robot = authed_peer(core, "127.0.0.2")
    for i in range(2):
        core.on_binary(robot, latched(f"/husky1/t{i}", "x" * 1000))
    alice = authed_peer(core, token=ALICE)
    subscribe(core, alice, "/husky1/t0")
    subscribe(core, alice, "/husky1/t0", on=False)
    subscribe(core, alice, "/husky1/t.*")  # t0 again and t1: one more than the bound
    assert [t for t, _ in binaries(alice)] == ["/husky1/t0", "/husky1/t0"]
    assert core.metrics.drops == {"/husky1/t1": 1}


def test_auth_reload_forgets_latched_messages_of_revoked_senders() -> None:
    core = make_core()
    robot, alice = authed_peer(core, "127.0.0.2"), authed_peer(core, token=ALICE)
    husky2 = authed_peer(core, "127.0.0.3")
    core.on_binary(robot, latched("/husky1/map", "m"))
    core.on_binary(robot, latched("/husky1/tf_static", "tf"))
    core.on_binary(husky2, latched("/husky2/map", "m2"))
    core.on_binary(alice, latched("/elsewhere/x", "x"))
    raw = copy.deepcopy(AUTH)
    identities: list[dict[str, Any]] = raw["identities"]  # type: ignore[assignment]
    raw["identities"] = [i for i in identities if i["name"] != "husky2"]  # robot deleted
    husky1 = next(i for i in identities if i["name"] == "husky1")
    husky1["rules"][0] = {"topic": "/husky1/map", "op": "send"}  # narrowed
    core.reload_auth(auth_map(raw))
    assert sorted(core.latched.topics()) == ["/elsewhere/x", "/husky1/map"]
    assert core.metrics.latched_events["revoked"] == 2


def test_a_resumed_session_gets_the_latched_messages_again() -> None:
    core = make_core()
    robot = authed_peer(core, "127.0.0.2")
    core.on_binary(robot, latched("/husky1/map", "m", no_drop=True))
    viewer = authed_peer(core, token=ALICE, session="tab1")
    subscribe(core, viewer, "/husky1/map")
    assert [t for t, _ in binaries(viewer)] == ["/husky1/map"]
    core.close_peer(viewer)
    again = authed_peer(core, token=ALICE, session="tab1")
    assert [t for t, _ in binaries(again)] == ["/husky1/map"]
    subscribe(core, again, "/husky1/map")  # the client's own resubscribe: nothing more
    assert binaries(again) == []


_FUZZ_BASE = fast_split(latched("/husky1/map", "z" * 3000), topic="/husky1/map",
                        message_id=2, max_fragment_bytes=700, no_drop=False)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_mutated_latched_frames_from_an_allowed_sender_never_crash(data: st.DataObject) -> None:
    core = make_core(max_malformed_in_row=10**6, latched_bytes=8000)
    robot, alice = authed_peer(core, "127.0.0.2"), authed_peer(core, token=ALICE)
    for _ in range(data.draw(st.integers(1, 12))):
        frame = bytearray(data.draw(st.sampled_from([*_FUZZ_BASE,
                                                     latched("/husky1/a", "a")])))
        for _ in range(data.draw(st.integers(0, 6))):
            frame[data.draw(st.integers(0, len(frame) - 1))] = data.draw(st.integers(0, 255))
        core.on_binary(robot, bytes(frame))  # must not raise
    assert core.latched.nbytes <= 8000
    subscribe(core, alice, ".*")  # whatever was kept is served without error
    assert core.metrics.latched_delivered == len(
        [f for t, f in alice.outbound.pop_batch(10**9) if isinstance(f, bytes)])
