"""The robots the auth map expects and the registry has not seen: in the robot list the
page asks for (``list_robots``) and in ``/robots``, through a real relay."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import parse_auth_map
from fleetctl.server.expectedrobots import expected_robots
from fleetctl.wire.control import encode_status
from tests.server.conftest import (
    ALICE_TOKEN,
    AUTH,
    BOB_TOKEN,
    auth_map,
    client,
    next_json,
    sha,
    wait_for,
)
from tests.server.test_app import http_get


def identity(name: str, rules: list[dict[str, str]], **kind: str) -> dict[str, Any]:
    return {"name": name, **kind, "rules": rules}


def test_robots_are_single_addresses_that_may_send_their_own_status() -> None:
    status = [{"topic": "/r1/status", "op": "send"}]
    raw = {"version": 1, "identities": [
        identity("r1", status, ip="10.8.0.2"),
        identity("r6", [{"topic": "/r6/.*", "op": "both"}], ip="fd00::6"),
        identity("lab", [{"topic": ".*", "op": "send"}], cidr="10.9.0.0/24"),  # a subnet
        identity("ops", [{"topic": ".*", "op": "both"}], token_sha256=sha("t" * 32)),
        identity("cam", [{"topic": "/cam/image", "op": "send"}], ip="10.8.0.7"),  # no status
        identity("a/b", [{"topic": ".*", "op": "send"}], ip="10.8.0.8"),  # not one segment
    ]}
    assert expected_robots(parse_auth_map(raw, Path("auth.yaml"))) == ("r1", "r6")


async def test_unseen_robots_are_listed_as_never_connected_to_whoever_may_see_them(
    make_server: Callable[..., RelayServer],
) -> None:
    async with make_server() as srv:
        async with client(srv, token=ALICE_TOKEN) as alice:
            await alice.send(json.dumps({"type": "list_robots"}))
            robots = (await next_json(alice, "robots"))["robots"]
            assert [(r["name"], r["online"], r["never_connected"], r["last_seen_s"])
                    for r in robots] == [("husky1", False, True, None),
                                         ("husky2", False, True, None)]
            async with client(srv, source="127.0.0.2") as husky1:
                await husky1.send(encode_status("husky1", status="OK", is_ok=True,
                                                battery_level=0.5))
                await wait_for(lambda: srv.registry.get("husky1") is not None)
                await alice.send(json.dumps({"type": "list_robots"}))
                husky1_json, husky2_json = (await next_json(alice, "robots"))["robots"]
                assert husky1_json["name"] == "husky1" and husky1_json["online"] is True
                assert "never_connected" not in husky1_json
                assert husky1_json["last_seen_s"] is not None
                assert husky2_json["name"] == "husky2" and husky2_json["never_connected"]
        # bob may receive husky1's topics only: husky2 is not his to see, seen or not.
        status, body = await http_get(srv.port, "/robots",
                                      {"Authorization": f"Bearer {BOB_TOKEN}"})
        assert status == 200 and [r["name"] for r in json.loads(body)["robots"]] == ["husky1"]
        status, body = await http_get(srv.port, "/robots")  # loopback: every robot
        assert [(r["name"], r.get("never_connected", False))
                for r in json.loads(body)["robots"]] == [("husky1", False), ("husky2", True)]


async def test_a_robot_added_to_the_auth_map_is_listed_at_once(
    make_server: Callable[..., RelayServer],
) -> None:
    async with make_server() as srv, client(srv, token=ALICE_TOKEN) as alice:
        raw = {**AUTH, "identities": [*AUTH["identities"], identity(
            "jackal1", [{"topic": "/jackal1/.*", "op": "send"}], ip="127.0.0.4")]}
        srv.core.reload_auth(auth_map(raw))
        await alice.send(json.dumps({"type": "list_robots"}))
        names = [r["name"] for r in (await next_json(alice, "robots"))["robots"]]
        assert names == ["husky1", "husky2", "jackal1"]
