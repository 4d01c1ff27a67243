"""auth.yaml live reload: file changes and SIGHUP, with real connections on 127.0.0.1."""

from __future__ import annotations

import asyncio
import copy
import json
import logging
import os
import signal
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from fleetctl.server.app import RelayServer, run_server
from fleetctl.server.authmap import load_auth_map
from fleetctl.server.config import ServerConfig, ServerLimits
from tests.server.conftest import (
    ALICE_TOKEN,
    AUTH,
    BOB_TOKEN,
    client,
    next_binary,
    next_json,
    subscribe,
    wait_for,
)
from tests.server.test_app import closed_code
from tests.support import decode_text, string_frame


def write_auth(path: Path, raw: dict[str, Any]) -> None:
    """Replace *path* the way deployments do: write a temporary file, rename it over."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(yaml.safe_dump(raw))
    os.replace(tmp, path)


def without(name: str) -> dict[str, Any]:
    raw = copy.deepcopy(AUTH)
    raw["identities"] = [i for i in raw["identities"] if i["name"] != name]
    return raw


def with_identity(identity: dict[str, Any]) -> dict[str, Any]:
    raw = copy.deepcopy(AUTH)
    raw["identities"].append(identity)
    return raw


@pytest.fixture
def auth_file(tmp_path: Path) -> Path:
    path = tmp_path / "auth.yaml"
    write_auth(path, AUTH)
    return path


@pytest.fixture
async def live(auth_file: Path, tmp_path: Path) -> AsyncIterator[RelayServer]:
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=auth_file,
                          database=tmp_path / "fleet.db",
                          limits=ServerLimits(auth_timeout_s=0.3))
    async with RelayServer(config) as srv:
        yield srv


async def test_removed_token_is_closed_within_1s_others_keep_receiving(
    live: RelayServer, auth_file: Path
) -> None:
    async with client(live, token=ALICE_TOKEN) as alice, \
            client(live, token=BOB_TOKEN) as bob, \
            client(live, source="127.0.0.2") as robot:
        await next_json(robot, "welcome")
        for ws in (alice, bob):
            assert (await subscribe(ws, "/husky1/.*"))["type"] == "subscribed"
        await robot.send(string_frame("/husky1/chat", "before"))
        assert decode_text(await next_binary(bob)) == "before"
        assert decode_text(await next_binary(alice)) == "before"
        peers_before = set(live.core.peers)

        write_auth(auth_file, without("bob"))
        started = time.monotonic()
        assert await closed_code(bob) == 4403
        assert time.monotonic() - started < 1.0
        assert bob.close_reason is not None and "revoked" in bob.close_reason

        # The robot and alice kept their connections (no reconnect) and still flow.
        await robot.send(string_frame("/husky1/chat", "after"))
        assert decode_text(await next_binary(alice)) == "after"
        assert set(live.core.peers) <= peers_before and len(live.core.peers) == 2
        assert live.metrics.auth_reloads == 1 and live.metrics.auth_reload_failures == 0
        text = live.metrics.render()
        assert "fleetctl_auth_reloads_total 1" in text
        assert "fleetctl_auth_reload_failures_total 0" in text
    async with client(live, token=BOB_TOKEN) as again:
        assert await closed_code(again) == 4401  # the token is refused from now on


async def test_narrowed_rules_stop_deliveries_without_reconnecting(
    live: RelayServer, auth_file: Path
) -> None:
    async with client(live, token=ALICE_TOKEN) as alice, \
            client(live, source="127.0.0.2") as husky1, \
            client(live, source="127.0.0.3") as husky2:
        assert (await subscribe(alice, ".*"))["type"] == "subscribed"
        assert (await subscribe(alice, "/husky1/chat"))["type"] == "subscribed"
        await husky1.send(string_frame("/husky1/chat", "one"))
        assert decode_text(await next_binary(alice)) == "one"

        raw = copy.deepcopy(AUTH)
        alice_entry = next(i for i in raw["identities"] if i["name"] == "alice")
        alice_entry["rules"] = [{"topic": "/husky2/.*", "op": "receive"}]
        write_auth(auth_file, raw)
        welcome = await next_json(alice, "welcome", timeout_s=1.0)
        assert welcome["rules"] == [{"topic": "/husky2/.*", "op": "receive"}]
        refused = await next_json(alice, "error")
        assert refused["code"] == "subscription_refused" and refused["topic"] == "/husky1/chat"
        assert (await next_json(alice, "unsubscribed"))["topic_regex"] == "/husky1/chat"

        await husky1.send(string_frame("/husky1/chat", "not any more"))
        await husky2.send(string_frame("/husky2/chat", "still"))
        # The ".*" pattern stays, filtered by the new receive rules: only husky2 arrives.
        assert decode_text(await next_binary(alice)) == "still"
        # Alice may no longer send either (was "both" on everything).
        await alice.send(string_frame("/husky1/goal_pose", "go"))
        assert (await next_json(alice, "error"))["code"] == "unauthorized_send"


async def test_new_robot_address_is_accepted_without_restart(
    live: RelayServer, auth_file: Path
) -> None:
    async with client(live, source="127.0.0.4") as stranger:
        assert await closed_code(stranger) == 4403  # no identity, no token frame
    write_auth(auth_file, with_identity(
        {"name": "husky4", "ip": "127.0.0.4", "rules": [{"topic": "/husky4/.*", "op": "send"}]}
    ))
    await wait_for(lambda: live.metrics.auth_reloads == 1, 2.0)
    async with client(live, source="127.0.0.4") as robot, \
            client(live, token=ALICE_TOKEN) as alice:
        assert (await next_json(robot, "welcome"))["identities"] == ["husky4"]
        await subscribe(alice, "/husky4/.*")
        await robot.send(string_frame("/husky4/chat", "new robot"))
        assert decode_text(await next_binary(alice)) == "new robot"


async def test_broken_file_keeps_the_old_map(
    live: RelayServer, auth_file: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="fleetctl.server")
    async with client(live, token=ALICE_TOKEN) as alice:
        await next_json(alice, "welcome")
        broken = copy.deepcopy(AUTH)
        broken["identities"][2]["rules"][0]["op"] = "sometimes"
        write_auth(auth_file, broken)
        await wait_for(lambda: live.metrics.auth_reload_failures == 1, 2.0)
        errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
        assert len(errors) == 1, errors
        assert str(auth_file) in errors[0] and "'op'" in errors[0] and "alice" in errors[0]
        # The old map stays: alice is still connected, and a new token connection works.
        async with client(live, token=BOB_TOKEN) as bob:
            assert (await next_json(bob, "welcome"))["identities"] == ["bob"]
        await alice.send(json.dumps({"type": "list_robots"}))
        await next_json(alice, "robots")
        assert live.metrics.auth_reloads == 0

        write_auth(auth_file, without("bob"))  # fixed (and changed): applied
        await wait_for(lambda: live.metrics.auth_reloads == 1, 2.0)
        infos = [r.getMessage() for r in caplog.records if "auth map reloaded" in r.getMessage()]
        assert len(infos) == 1 and "file changed" in infos[0]


async def test_a_deeply_nested_file_is_one_error_line_and_keeps_the_old_map(
    live: RelayServer, auth_file: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="fleetctl.server")
    auth_file.write_text("identities: " + "[" * 2000 + "]" * 2000 + "\n")
    assert not live.reload_auth("SIGHUP")  # a RecursionError in PyYAML before
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].exc_info is None
    assert "nested too deeply" in errors[0].getMessage()
    async with client(live, token=BOB_TOKEN) as bob:
        assert (await next_json(bob, "welcome"))["identities"] == ["bob"]


async def test_sighup_reloads(auth_file: Path, tmp_path: Path) -> None:
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=auth_file,
                          database=tmp_path / "fleet.db")
    stop = asyncio.Event()
    started: list[RelayServer] = []

    def ready(srv: RelayServer) -> None:
        srv.reloader.poll_interval_s = 3600.0  # only SIGHUP may reload in this test
        started.append(srv)

    task = asyncio.create_task(run_server(config, ready=ready, stop=stop))
    try:
        await wait_for(lambda: bool(started))
        srv = started[0]
        async with client(srv, token=BOB_TOKEN) as bob:
            await next_json(bob, "welcome")
            write_auth(auth_file, without("bob"))
            os.kill(os.getpid(), signal.SIGHUP)
            assert await closed_code(bob) == 4403
        assert srv.metrics.auth_reloads == 1
        assert "bob" not in [i.name for i in srv.auth.identities]
    finally:
        stop.set()
        await asyncio.wait_for(task, 10)


async def test_offline_session_of_a_removed_identity_is_dropped(
    make_server: Callable[..., RelayServer], auth_file: Path
) -> None:
    from fleetctl.server.sessions import SESSION_HEADER

    async with make_server(auth=load_auth_map(auth_file)) as srv:
        async with client(srv, token=BOB_TOKEN,
                          additional_headers={SESSION_HEADER: "laptop"}) as bob:
            await subscribe(bob, "/husky1/.*")
        await wait_for(lambda: srv.core.sessions.offline_count == 1)
        write_auth(auth_file, without("bob"))
        await wait_for(lambda: srv.metrics.auth_reloads == 1, 2.0)
        assert len(srv.core.sessions) == 0
