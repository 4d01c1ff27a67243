"""The replicas' interest as one replica sees it (no NATS: entries are fed as the bucket's
watch would; the real bucket is tested in test_replicas.py::test_no_interest_no_frames)."""

from __future__ import annotations

import json

import pytest

from fleetctl.server.cluster.config import ClusterConfig
from fleetctl.server.cluster.remoteinterest import (
    MAX_VALUE_BYTES,
    TTL_S,
    RemoteInterest,
    decode_subjects,
    encode_subjects,
)
from tests.support import ManualClock


def board(clock: ManualClock) -> RemoteInterest:
    config = ClusterConfig(name="relay-a", nats_urls=("nats://127.0.0.1:4222",))
    return RemoteInterest(config, clock)


def value(*subjects: str) -> bytes:
    return encode_subjects("fleetctl", subjects)


def synced(clock: ManualClock) -> RemoteInterest:
    interest = board(clock)
    interest.on_entry("relay-a", value(), None)  # our own write came back
    interest.synced = True  # the watch's end-of-contents marker
    interest._changed()
    return interest


def test_in_doubt_every_frame_is_published() -> None:
    clock = ManualClock(1_000.0)
    interest = board(clock)
    interest.on_entry("relay-b", value(), None)  # B wants nothing...
    assert interest.wants("fleetctl.husky1.pose")  # ...but the bucket is not read yet
    interest.synced = True
    assert interest.wants("fleetctl.husky1.pose")  # our own write has not come back
    interest.on_entry("relay-a", value(), None)
    assert not interest.wants("fleetctl.husky1.pose")
    clock.now_s += TTL_S + 1  # our writes stopped coming back: JetStream away?
    interest._expire()
    assert interest.wants("fleetctl.husky1.pose")
    assert interest.known() == {"relay-b": frozenset()}  # and nobody is forgotten


def test_exact_and_wide_subjects_of_other_replicas_only() -> None:
    clock = ManualClock(1_000.0)
    interest = synced(clock)
    interest.on_entry("relay-a", value("fleetctl.husky9.>"), None)  # our own: not asked
    interest.on_entry("relay-b", value("fleetctl.husky1.status", "fleetctl.husky2.>"), None)
    assert interest.wants("fleetctl.husky1.status")
    assert not interest.wants("fleetctl.husky1.pose")
    assert interest.wants("fleetctl.husky2.cam.image")
    assert not interest.wants("fleetctl.husky9.pose")
    # A change replaces the memoised answers.
    interest.on_entry("relay-b", value("fleetctl.>"), None)
    assert interest.wants("fleetctl.husky1.pose")
    interest.on_entry("relay-b", None, "DEL")  # B stopped cleanly
    assert not interest.wants("fleetctl.husky1.pose")


def test_a_replica_not_heard_of_for_the_ttl_is_forgotten() -> None:
    clock = ManualClock(1_000.0)
    interest = synced(clock)
    interest.on_entry("relay-b", value("fleetctl.husky1.>"), None)
    clock.now_s += TTL_S / 2
    interest.on_entry("relay-a", value(), None)  # our refresh
    interest._expire()
    assert interest.wants("fleetctl.husky1.pose")
    clock.now_s += TTL_S / 2 + 1
    interest.on_entry("relay-a", value(), None)
    interest._expire()
    assert interest.known() == {} and interest.counters["expired"] == 1
    assert not interest.wants("fleetctl.husky1.pose")


def test_a_malformed_value_counts_as_everything() -> None:
    clock = ManualClock(1_000.0)
    interest = synced(clock)
    interest.on_entry("relay-b", b"{not json", None)
    assert interest.wants("fleetctl.anything.at.all")
    assert interest.counters["malformed"] == 1


@pytest.mark.parametrize("raw", [
    b"[]", b'{"subjects": "fleetctl.>"}', b'{"subjects": ["other.x"]}',
    b'{"subjects": ["fleetctl..x"]}', b'{"subjects": [1]}', b'{"subjects": ["fleetctl.a b"]}',
])
def test_decode_refuses_what_is_not_a_list_of_this_fleets_subjects(raw: bytes) -> None:
    with pytest.raises(ValueError):
        decode_subjects("fleetctl", raw)


def test_a_list_too_long_is_written_as_everything() -> None:
    many = [f"fleetctl.robot{i}.{'x' * 60}" for i in range(MAX_VALUE_BYTES // 60)]
    assert json.loads(encode_subjects("fleetctl", many)) == {"subjects": ["fleetctl.>"]}
    assert decode_subjects("fleetctl", encode_subjects("fleetctl", ["fleetctl.a.>"])) == {
        "fleetctl.a.>"}
