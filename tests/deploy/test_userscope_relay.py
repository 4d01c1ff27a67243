"""Users scoped to some robots, through a real relay loaded with the auth.yaml that
`add-user --robots` renders: the scoped viewer gets husky1's frames and robot entry and
not jackal2's, the scoped operator commands husky1 and is refused jackal2, and
`set-user --all-robots` reaches the open connection by the relay's auth reload
(docs/operator.md, "Users scoped to some robots")."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from fleetctl.deploy import operations as ops
from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerConfig
from tests.deploy.conftest import SeededKeySource
from tests.server.conftest import client, next_binary, next_json, subscribe
from tests.support import decode_text, string_frame

# The relay knows robots by their source address: a fleet on loopback addresses.
HUSKY1, JACKAL2 = "127.0.0.2", "127.0.0.3"


@pytest.fixture
def fleet_dir(tmp_path: Path) -> Path:
    fleet_dir = tmp_path / "fleet"
    keys = SeededKeySource()
    ops.create_fleet(fleet_dir, subnet="127.0.0.0/24", keys=keys)
    ops.add_robot(fleet_dir, "husky1", ip=HUSKY1, keys=keys)
    ops.add_robot(fleet_dir, "jackal2", ip=JACKAL2, keys=keys)
    return fleet_dir


@pytest.fixture
def tokens(fleet_dir: Path) -> dict[str, str]:
    """The users' tokens by role: the viewer and the operator scoped to husky1."""
    out = {}
    for role, robots in (("viewer", ["husky1"]), ("operator", ["husky1"]), ("admin", None)):
        token = ops.add_user(fleet_dir, f"{role}@example.com", role, robots=robots).token
        assert token is not None
        out[role] = token.reveal()
    return out


@pytest.fixture
async def relay(fleet_dir: Path, tokens: dict[str, str],
                tmp_path: Path) -> AsyncIterator[RelayServer]:
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0,
                          auth_map=fleet_dir / "server" / "auth.yaml",
                          database=tmp_path / "fleet.db")
    async with RelayServer(config) as srv:
        yield srv


async def _robot_names(ws: Any) -> list[str]:
    await ws.send(json.dumps({"type": "list_robots"}))
    return [r["name"] for r in (await next_json(ws, "robots"))["robots"]]


async def _relayed(sender: Any, topic: str, text: str, witness: Any) -> None:
    """Send, and wait until *witness* (subscribed to everything) has it: the relay then
    queued it for every subscriber, each connection's queue in order."""
    await sender.send(string_frame(topic, text))
    assert decode_text(await next_binary(witness)) == text


async def test_a_scoped_viewer_sees_only_its_robots(relay: RelayServer, fleet_dir: Path,
                                                    tokens: dict[str, str]) -> None:
    async with client(relay, token=tokens["viewer"]) as viewer, \
            client(relay, token=tokens["admin"]) as admin, \
            client(relay, source=HUSKY1) as husky1, client(relay, source=JACKAL2) as jackal2:
        welcome = await next_json(viewer, "welcome")
        assert welcome["rules"] == [{"topic": "/husky1/.*", "op": "receive"}]
        for ws in (husky1, jackal2):
            await next_json(ws, "welcome")
        assert (await subscribe(viewer, ".*"))["type"] == "subscribed"
        assert (await subscribe(admin, ".*"))["type"] == "subscribed"
        assert await _robot_names(viewer) == ["husky1"]
        assert await _robot_names(admin) == ["husky1", "jackal2"]

        await _relayed(jackal2, "/jackal2/chat", "from jackal2", admin)
        await _relayed(husky1, "/husky1/chat", "from husky1", admin)
        # jackal2's frame went first: had it been queued for the viewer, it would be here.
        assert decode_text(await next_binary(viewer)) == "from husky1"

        # The scope widened while connected: auth.yaml re-rendered, reloaded by the relay.
        ops.set_user_robots(fleet_dir, "viewer@example.com", None)
        welcome = await next_json(viewer, "welcome")
        assert welcome["rules"] == [{"topic": "/[^/]+/.*", "op": "receive"}]
        assert await _robot_names(viewer) == ["husky1", "jackal2"]
        await _relayed(jackal2, "/jackal2/chat", "jackal2 again", admin)
        assert decode_text(await next_binary(viewer)) == "jackal2 again"


async def test_a_scoped_operator_commands_only_its_robots(relay: RelayServer,
                                                          tokens: dict[str, str]) -> None:
    async with client(relay, token=tokens["operator"]) as operator, \
            client(relay, token=tokens["admin"]) as admin, \
            client(relay, source=HUSKY1) as husky1, client(relay, source=JACKAL2) as jackal2:
        await next_json(operator, "welcome")
        for robot, name in ((husky1, "husky1"), (jackal2, "jackal2")):
            await next_json(robot, "welcome")
            assert (await subscribe(robot, f"/{name}/goal_pose"))["type"] == "subscribed"

        await operator.send(string_frame("/husky1/goal_pose", "go husky1"))
        assert decode_text(await next_binary(husky1)) == "go husky1"

        await operator.send(string_frame("/jackal2/goal_pose", "go jackal2"))
        refused = await next_json(operator, "error")
        assert (refused["code"], refused["topic"]) == ("unauthorized_send", "/jackal2/goal_pose")
        # The refused goal went nowhere: the next one jackal2 gets is the admin's.
        await admin.send(string_frame("/jackal2/goal_pose", "from admin"))
        assert decode_text(await next_binary(jackal2)) == "from admin"
