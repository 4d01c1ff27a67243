"""The robot registry shared by replicas through JetStream KV (real nats-server, real
replicas and WebSocket clients), and its key mapping and entry checks."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from fleetctl.server.app import RelayServer
from fleetctl.server.cluster.config import ClusterConfig, ClusterStartError
from fleetctl.server.cluster.kvkeys import key_token
from fleetctl.server.cluster.sharedregistry import SharedRegistry
from fleetctl.wire.control import encode_status
from tests.server.cluster.conftest import fanout
from tests.server.cluster.natsproc import NatsServer
from tests.server.conftest import ALICE_TOKEN, client, next_json
from tests.support import wait_until


def registry(clock: Callable[[], float]) -> SharedRegistry:
    return SharedRegistry(None, 5.0, ClusterConfig(name="relay-a", nats_urls=("nats://x",)),
                          clock=clock)


def entry(name: str, **fields: Any) -> bytes:
    data = {"name": name, "first_seen_s": 10.0, "last_seen_s": 100.0, "status": "ok",
            "is_ok": True, "battery_level": 0.5, "location": "lab", "status_time_s": 99.0,
            "live": True, **fields}
    return json.dumps(data).encode()


def test_another_replicas_robot_is_listed_and_falls_offline_when_not_refreshed() -> None:
    now = [101.0]
    reg = registry(lambda: now[0])
    reg.on_entry(f"{key_token('husky1')}.relay-b", entry("husky1"), None)
    assert reg.names() == ["husky1"] and reg.online("husky1")
    record = reg.get("husky1")
    assert record is not None and record.status == "ok" and record.battery_level == 0.5
    now[0] = 106.0  # relay-b died: its entry is not refreshed
    assert not reg.online("husky1")
    assert reg.as_json()[0]["online"] is False


def test_a_robot_that_moved_is_online_whatever_its_old_replica_said_last() -> None:
    reg = registry(lambda: 101.0)
    reg.on_entry(f"{key_token('husky1')}.relay-c", entry("husky1", live=True), None)
    reg.on_entry(f"{key_token('husky1')}.relay-b", entry("husky1", live=False,
                                                         last_seen_s=90.0), None)
    assert reg.online("husky1")


def test_own_entries_and_bad_entries_are_ignored_and_counted() -> None:
    reg = registry(lambda: 101.0)
    reg.on_entry(f"{key_token('husky1')}.relay-a", entry("husky1"), None)  # our own
    for value in (b"not json", entry("other"), entry("husky1", last_seen_s="x"),
                  entry("husky1", live="yes"), entry("husky1", battery_level=float("nan")),
                  entry("husky1", is_ok=1)):
        reg.on_entry(f"{key_token('husky1')}.relay-b", value, None)
    reg.on_entry("bad~key.relay-b", entry("husky1"), None)
    assert reg.names() == [] and reg.counters["malformed"] == 7


def test_a_deleted_entry_is_forgotten() -> None:
    reg = registry(lambda: 101.0)
    key = f"{key_token('husky1')}.relay-b"
    reg.on_entry(key, entry("husky1"), None)
    reg.on_entry(key, None, "DEL")
    assert reg.names() == []


@pytest.mark.slow
async def test_a_viewer_on_b_sees_the_robot_on_a_online_then_offline(
        make_replica: Callable[..., RelayServer], nats_server: NatsServer) -> None:
    a = make_replica("relay-a", [nats_server.url])
    b = make_replica("relay-b", [nats_server.url])
    async with a, b:
        async with client(b, token=ALICE_TOKEN) as viewer:
            await next_json(viewer, "welcome")

            async def robots_on_b() -> list[dict[str, Any]]:
                await viewer.send(json.dumps({"type": "list_robots"}))
                found: list[dict[str, Any]] = (await next_json(viewer, "robots"))["robots"]
                return found

            async with client(a, source="127.0.0.2") as robot:  # husky1, by address
                await next_json(robot, "welcome")
                await robot.send(encode_status("husky1", status="docking", is_ok=True,
                                               battery_level=0.25, location="bay 3"))
                listed = await until(robots_on_b, lambda rs: any(
                    r["name"] == "husky1" and r["online"] for r in rs))
                husky = next(r for r in listed if r["name"] == "husky1")
                assert husky["status"] == "docking" and husky["battery_level"] == 0.25
                assert husky["location"] == "bay 3"
            # The robot left A: B shows it offline, with its last status kept.
            listed = await until(robots_on_b, lambda rs: any(
                r["name"] == "husky1" and not r["online"] for r in rs))
            assert next(r for r in listed if r["name"] == "husky1")["status"] == "docking"
        shared = fanout(a).registry
        assert shared is not None
        # B may hear A's second write (both replicas share this event loop) before A's
        # put returns and is counted.
        await wait_until(lambda: shared.counters["puts"] >= 2, 5.0)
        assert shared.counters["put_failures"] == 0


async def until(read: Callable[[], Any], ok: Callable[[Any], bool],
                timeout_s: float = 10.0) -> Any:
    """Read again until *ok* holds, within *timeout_s* (the watch crosses NATS
    asynchronously)."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = await read()
        if ok(value):
            return value
        assert time.monotonic() < deadline, f"not reached in {timeout_s} s: {value}"
        await asyncio.sleep(0.05)  # polling interval of a deadline-bounded wait


@pytest.mark.slow
async def test_nats_without_jetstream_is_a_clear_start_error(
        make_replica: Callable[..., RelayServer], tmp_path: Path) -> None:
    plain = NatsServer("plain", tmp_path, jetstream=False)
    plain.start()
    try:
        replica = make_replica("relay-a", [plain.url])
        with pytest.raises(ClusterStartError, match=r"cluster\.state_replicas.*JetStream"):
            await replica.start()
        await replica.stop()
    finally:
        plain.stop()
