"""A latched message over ``latched_message_bytes`` through a real relay: relayed, not
kept, counted, and one WARNING per (sender, topic) naming the topic, its size and the
setting; the store's memory of what it said is bounded."""

from __future__ import annotations

import logging
from collections.abc import Callable

import pytest

from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerLimits
from fleetctl.server.latched import LatchedStore
from fleetctl.server.metrics import Metrics
from fleetctl.wire.codec import default_codec
from fleetctl.wire.fragmenter import fast_split
from fleetctl.wire.fragments import read_fragment_header
from fleetctl.wire.metadata import read_root
from tests.server.conftest import client, wait_for

LIMIT = 4096


def latched(topic: str, size: int) -> bytes:
    codec = default_codec()
    cls = codec.registry.get("std_msgs/msg/String").cls
    return codec.encode(cls("m" * size), "std_msgs/msg/String", topic, latched=True)


def said(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "fleetctl.server.latched" and r.levelno == logging.WARNING]


async def test_a_latched_message_too_big_to_keep_is_said_once_per_sender_and_topic(
        make_server: Callable[..., RelayServer], caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="fleetctl.server.latched")
    limits = ServerLimits(latched_message_bytes=LIMIT)
    async with make_server(limits=limits) as srv, \
            client(srv, source="127.0.0.2") as husky1, \
            client(srv, source="127.0.0.3") as husky2:
        events = srv.core.metrics.latched_events
        big = latched("/husky1/map", 3 * LIMIT)
        for _ in range(3):  # a map republished: said once
            await husky1.send(big)
        await wait_for(lambda: events.get("refused_too_big", 0) == 3)
        await husky1.send(latched("/husky1/map_small", 10))  # kept: nothing said
        await husky2.send(latched("/husky2/map", 2 * LIMIT))  # another sender and topic
        await wait_for(lambda: events.get("refused_too_big", 0) == 4
                       and events.get("stored", 0) == 1)
        lines = said(caplog)
        assert len(lines) == 2, lines
        first, second = lines
        assert "/husky1/map " in first and "husky1" in first
        assert f"{len(big)} bytes" in first
        assert f"limits.latched_message_bytes ({LIMIT})" in first
        assert "/husky2/map " in second and "husky2" in second


def test_fragments_of_a_message_too_big_name_its_declared_size(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="fleetctl.server.latched")
    store = LatchedStore(1 << 20, LIMIT, Metrics())
    whole = latched("/husky1/cloud", 4 * LIMIT)
    for message_id in (1, 2):  # the same topic again: said once
        for part in fast_split(whole, topic="/husky1/cloud", message_id=message_id,
                               max_fragment_bytes=1024, no_drop=False):
            meta, root = read_root(part)
            store.put(("husky1",), meta.topic, part, read_fragment_header(part, root))
    lines = said(caplog)
    assert len(lines) == 1 and "/husky1/cloud" in lines[0], lines
    assert f"{len(whole)} bytes" in lines[0]


def test_what_was_said_is_bounded(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="fleetctl.server.latched")
    store = LatchedStore(1 << 20, 100, Metrics(), max_entries=4)
    big = {f"/husky1/t{k}": latched(f"/husky1/t{k}", 200) for k in range(6)}
    for topic, frame in big.items():
        store.put(("husky1",), topic, frame, None)
    assert len(said(caplog)) == 6
    assert len(store._warned) == 4  # the two oldest forgotten
    store.put(("husky1",), "/husky1/t5", big["/husky1/t5"], None)  # still remembered
    store.put(("husky1",), "/husky1/t0", big["/husky1/t0"], None)  # forgotten: said again
    assert len(said(caplog)) == 7
    # A store whose total bound is the smaller one names that setting.
    small = LatchedStore(150, 1000, Metrics())
    small.put(("husky1",), "/husky1/t0", big["/husky1/t0"], None)
    assert "limits.latched_bytes (150)" in said(caplog)[-1]
