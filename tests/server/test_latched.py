"""Unit tests of the latched store (no relay, no sockets)."""

from __future__ import annotations

import random

import pytest

from fleetctl.server.latched import LatchedStore
from fleetctl.server.metrics import Metrics
from fleetctl.wire.codec import default_codec
from fleetctl.wire.fragments import Reassembler, read_fragment_header, split
from fleetctl.wire.metadata import read_metadata, read_root

ROBOT = ("husky1",)
OTHER = ("husky2",)


def frame(topic: str, text: str, *, seq: int = 1) -> bytes:
    codec = default_codec()
    cls = codec.registry.get("std_msgs/msg/String").cls
    return codec.encode(cls(text), "std_msgs/msg/String", topic, seq=seq, latched=True)


def fragments_of(whole: bytes, message_id: int, max_bytes: int = 600) -> list[bytes]:
    topic = read_metadata(whole).topic
    return split(whole, topic=topic, message_id=message_id, max_fragment_bytes=max_bytes,
                 no_drop=False)


def put(store: LatchedStore, sender: tuple[str, ...], f: bytes) -> None:
    meta, root = read_root(f)
    header = read_fragment_header(f, root) if meta.type == "fleetctl_msgs/msg/Fragment" else None
    store.put(sender, meta.topic, f, header)


def reassemble(frames: list[bytes]) -> bytes | None:
    r = Reassembler(1 << 24, 10.0)
    out = [r.feed(f, 0.0) for f in frames]
    return out[-1]


def make(max_bytes: int = 1 << 20, max_message_bytes: int = 1 << 20,
         **kw: int) -> tuple[LatchedStore, Metrics]:
    metrics = Metrics()
    return LatchedStore(max_bytes, max_message_bytes, metrics, **kw), metrics


def test_keeps_the_newest_whole_message_per_sender_and_topic() -> None:
    store, metrics = make()
    put(store, ROBOT, frame("/husky1/map", "v1"))
    put(store, ROBOT, frame("/husky1/map", "v2"))
    put(store, OTHER, frame("/husky1/map", "from another sender"))
    put(store, ROBOT, frame("/husky1/tf_static", "tf"))
    assert store.messages("/husky1/map") == [[frame("/husky1/map", "v2")],
                                            [frame("/husky1/map", "from another sender")]]
    assert sorted(store.topics()) == ["/husky1/map", "/husky1/tf_static"]
    assert len(store) == 3 and metrics.latched_messages == 3
    assert store.nbytes == metrics.latched_bytes == sum(
        len(f) for t in store.topics() for m in store.messages(t) for f in m)
    assert store.messages("/nothing") == []


def test_fragments_are_stored_once_complete_in_index_order() -> None:
    store, _ = make()
    whole = frame("/husky1/map", "m" * 5000)
    parts = fragments_of(whole, message_id=7)
    assert len(parts) > 3
    shuffled = parts[:]
    random.Random(1).shuffle(shuffled)
    for i, part in enumerate(shuffled):
        assert store.messages("/husky1/map") == []  # incomplete: nothing to serve
        put(store, ROBOT, part)
        if i == 1:
            put(store, ROBOT, part)  # a duplicate fragment changes nothing
    [stored] = store.messages("/husky1/map")
    assert stored == parts
    assert reassemble(stored) == whole


def test_incomplete_newer_message_keeps_serving_the_last_complete_one() -> None:
    store, metrics = make()
    old, new, newer = (frame("/husky1/map", c * 3000) for c in "abc")
    for part in fragments_of(old, 1):
        put(store, ROBOT, part)
    new_parts = fragments_of(new, 2)
    for part in new_parts[:-1]:
        put(store, ROBOT, part)
    assert reassemble(store.messages("/husky1/map")[0]) == old
    for part in fragments_of(newer, 3):  # message 2 never completes: superseded
        put(store, ROBOT, part)
    put(store, ROBOT, new_parts[-1])  # a late fragment of the superseded message
    assert reassemble(store.messages("/husky1/map")[0]) == newer
    assert metrics.latched_events["superseded"] == 1


def test_a_whole_frame_replaces_fragments_and_the_reverse() -> None:
    store, _ = make()
    for part in fragments_of(frame("/husky1/map", "x" * 3000), 1):
        put(store, ROBOT, part)
    small = frame("/husky1/map", "small")
    put(store, ROBOT, small)
    assert store.messages("/husky1/map") == [[small]]
    big = frame("/husky1/map", "y" * 3000)
    parts = fragments_of(big, 2)
    for part in parts:
        put(store, ROBOT, part)
    assert store.messages("/husky1/map") == [parts]
    for part in parts:  # a resend of the stored message (after a reconnect): ignored
        put(store, ROBOT, part)
    assert store.messages("/husky1/map") == [parts] and len(store) == 1


def test_byte_bound_evicts_least_recently_updated_and_counts() -> None:
    one = len(frame("/husky1/a", "x" * 400))
    store, metrics = make(max_bytes=3 * one + 10)
    for name in "abc":
        put(store, ROBOT, frame(f"/husky1/{name}", "x" * 400))
    put(store, ROBOT, frame("/husky1/a", "y" * 400))  # a is now the most recent
    put(store, ROBOT, frame("/husky1/d", "x" * 400))  # evicts b, the least recent
    assert sorted(store.topics()) == ["/husky1/a", "/husky1/c", "/husky1/d"]
    assert metrics.latched_events["evicted"] == 1
    assert store.nbytes <= store.max_bytes


def test_incomplete_messages_count_against_the_byte_bound() -> None:
    whole = frame("/husky1/map", "m" * 6000)
    parts = fragments_of(whole, 1)
    small = frame("/husky1/small", "s")
    pending = sum(len(p) for p in parts[:-1])
    store, metrics = make(max_bytes=len(small) + pending - 1)
    assert len(whole) <= store.max_message_bytes and pending <= store.max_message_bytes
    put(store, ROBOT, small)
    for part in parts[:-1]:
        put(store, ROBOT, part)
    assert store.nbytes <= store.max_bytes
    assert "/husky1/small" not in store.topics() and metrics.latched_events["evicted"] >= 1


def test_entry_bound_evicts_the_oldest_key() -> None:
    store, metrics = make(max_entries=2)
    for name in "abc":
        put(store, ROBOT, frame(f"/husky1/{name}", name))
    assert sorted(store.topics()) == ["/husky1/b", "/husky1/c"]
    assert metrics.latched_events["evicted"] == 1


@pytest.mark.parametrize("fragmented", [False, True])
def test_a_message_over_the_per_message_bound_is_refused_and_the_older_one_forgotten(
        fragmented: bool) -> None:
    store, metrics = make(max_message_bytes=2000)
    put(store, ROBOT, frame("/husky1/map", "old"))
    big = frame("/husky1/map", "b" * 3000)
    for part in fragments_of(big, 5) if fragmented else [big]:
        put(store, ROBOT, part)
    assert store.messages("/husky1/map") == []  # never the stale one
    assert metrics.latched_events["refused_too_big"] == 1  # once per message, not per part
    assert store.nbytes == 0 and len(store) == 0


def test_contradicting_fragments_are_dropped_and_counted() -> None:
    store, metrics = make()
    a = fragments_of(frame("/husky1/map", "a" * 3000), 4)
    b = fragments_of(frame("/husky1/map", "b" * 4000), 4)  # same id, other count/total
    put(store, ROBOT, a[0])
    put(store, ROBOT, b[1])
    assert metrics.latched_events["malformed"] == 1
    assert store.messages("/husky1/map") == [] and store.nbytes == 0


def test_drop_where_forgets_revoked_senders() -> None:
    store, metrics = make()
    put(store, ROBOT, frame("/husky1/map", "m"))
    put(store, OTHER, frame("/husky2/map", "m"))
    assert store.drop_where(lambda sender, topic: sender == ROBOT) == 1
    assert store.topics() == ["/husky2/map"]
    assert metrics.latched_events["revoked"] == 1 and metrics.latched_messages == 1


class Heard:
    """A LatchedListener that writes down what it is told."""

    def __init__(self) -> None:
        self.events: list[tuple[str, tuple[str, ...], str, int]] = []

    def stored(self, sender: tuple[str, ...], topic: str, frames: list[bytes]) -> None:
        self.events.append(("stored", sender, topic, len(frames)))

    def forgotten(self, sender: tuple[str, ...], topic: str) -> None:
        self.events.append(("forgotten", sender, topic, 0))


def test_the_listener_hears_local_messages_stored_refused_and_revoked() -> None:
    store = LatchedStore(1 << 20, 3000, Metrics())
    heard = Heard()
    store.listener = heard
    whole = frame("/husky1/map", "m" * 2000)
    parts = fragments_of(whole, 7)
    for f in parts:
        put(store, ROBOT, f)
    put(store, ROBOT, frame("/husky1/map", "x" * 4000))  # too big: the older one goes too
    put(store, OTHER, frame("/husky2/map", "y"))
    store.drop_where(lambda sender, _topic: sender == OTHER)
    assert heard.events == [("stored", ROBOT, "/husky1/map", len(parts)),
                            ("forgotten", ROBOT, "/husky1/map", 0),
                            ("stored", OTHER, "/husky2/map", 1),
                            ("forgotten", OTHER, "/husky2/map", 0)]


def test_remote_messages_are_served_replaced_and_forgotten_without_the_listener() -> None:
    metrics = Metrics()
    store = LatchedStore(1 << 20, 1 << 16, metrics)
    heard = Heard()
    store.listener = heard
    remote = fragments_of(frame("/husky1/map", "r" * 2000), 3)
    assert store.put_remote(ROBOT, "/husky1/map", remote)
    assert store.messages("/husky1/map") == [remote] and len(store) == 1
    assert store.nbytes == sum(map(len, remote))
    assert store.forget_remote(ROBOT, "/husky1/map")
    assert store.messages("/husky1/map") == [] and store.nbytes == 0 and len(store) == 0
    # A local message stays when another replica forgets the key.
    local = frame("/husky1/map", "local")
    put(store, ROBOT, local)
    assert not store.forget_remote(ROBOT, "/husky1/map")
    assert store.messages("/husky1/map") == [[local]]
    # A newer remote message replaces the local one (the sender moved replicas).
    newer = [frame("/husky1/map", "newer")]
    assert store.put_remote(ROBOT, "/husky1/map", newer)
    assert store.messages("/husky1/map") == [newer] and store.nbytes == len(newer[0])
    assert not store.put_remote(OTHER, "/husky2/map", [bytes(1 << 17)])  # over the bound
    assert heard.events == [("stored", ROBOT, "/husky1/map", 1)]  # the local put only
    assert metrics.latched_events["remote_stored"] == 2
    assert metrics.latched_events["remote_forgotten"] == 1
    assert metrics.latched_events["refused_too_big"] == 1


def test_candidates_follow_the_stored_topics_and_their_order_under_churn() -> None:
    """What a new subscription is matched against (candidates) stays the stored topics,
    in topics() order, through stores, refusals, evictions, remote messages and
    revocations."""
    from fleetctl.server.regex import compile_full

    rng = random.Random(3)
    store, _ = make(max_message_bytes=2000, max_entries=40)
    names = [f"/husky{r}/t{i}" for r in (1, 2) for i in range(30)]
    everything, husky1 = compile_full(".*"), compile_full("/husky1/.*")
    for _ in range(1500):
        topic, sender, action = rng.choice(names), rng.choice([ROBOT, OTHER]), rng.random()
        if action < 0.6:
            put(store, sender, frame(topic, "m"))
        elif action < 0.7:
            put(store, sender, frame(topic, "b" * 3000))  # too big: the older one forgotten
        elif action < 0.8:
            store.put_remote(sender, topic, [frame(topic, "r")])
        elif action < 0.9:
            store.forget_remote(sender, topic)
        else:
            store.drop_where(lambda s, t, gone=topic: t == gone)
        assert store.candidates([everything]) == store.topics()
        assert store.candidates([husky1]) == [t for t in store.topics()
                                            if t.startswith("/husky1/")]
