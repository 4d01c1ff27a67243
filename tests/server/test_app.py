"""Integration tests: a real relay on 127.0.0.1:0 and real websockets clients."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from typing import Any

import pytest
from websockets.exceptions import ConnectionClosed

from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerLimits
from fleetctl.wire.control import encode_status
from fleetctl.wire.metadata import read_metadata
from tests.server.conftest import (
    ALICE_TOKEN,
    BOB_TOKEN,
    client,
    next_binary,
    next_json,
    subscribe,
    wait_for,
)
from tests.support import decode_text, string_frame


async def http_get(port: int, path: str, headers: dict[str, str] | None = None,
                   source: str = "127.0.0.1") -> tuple[int, str]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0))
    head = "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
    writer.write(f"GET {path} HTTP/1.1\r\nHost: x\r\n{head}\r\n".encode())
    data = await asyncio.wait_for(reader.read(), 5)
    writer.close()
    status_line, _, rest = data.decode().partition("\r\n")
    return int(status_line.split()[1]), rest.partition("\r\n\r\n")[2]


async def closed_code(ws: Any) -> int:
    with pytest.raises(ConnectionClosed):
        await asyncio.wait_for(_read_forever(ws), 5)
    code: int = ws.close_code
    return code


async def _read_forever(ws: Any) -> None:
    while True:
        await ws.recv()


async def test_relay_and_acl_on_send_and_receive(server: RelayServer) -> None:
    async with client(server, token=ALICE_TOKEN) as alice, \
            client(server, source="127.0.0.2") as robot, \
            client(server, token=BOB_TOKEN) as bob:
        welcome = await next_json(robot, "welcome")
        assert welcome["identities"] == ["husky1"]
        assert {"topic": "/husky1/.*", "op": "send"} in welcome["rules"]
        assert (await subscribe(alice, "/husky1/.*"))["type"] == "subscribed"
        assert (await subscribe(bob, ".*"))["type"] == "subscribed"  # filtered per delivery
        refused = await subscribe(robot, "/husky1/scan")
        assert refused["code"] == "subscription_refused" and refused["topic"] == "/husky1/scan"
        assert (await subscribe(robot, "/husky1/goal_pose"))["type"] == "subscribed"

        await robot.send(string_frame("/husky1/chat", "hello"))
        assert decode_text(await next_binary(alice)) == "hello"
        assert decode_text(await next_binary(bob)) == "hello"

        await robot.send(string_frame("/husky2/chat", "spoof"))  # not its topic
        err = await next_json(robot, "error")
        assert err["code"] == "unauthorized_send" and err["topic"] == "/husky2/chat"

        await alice.send(string_frame("/husky1/goal_pose", "go"))
        assert decode_text(await next_binary(robot)) == "go"
        await alice.send(string_frame("/elsewhere/x", "not for bob"))
        await alice.send(string_frame("/husky1/marker", "for bob"))
        # Bob's ".*" pattern never yields topics outside his receive rules.
        assert decode_text(await next_binary(bob)) == "go"
        assert decode_text(await next_binary(bob)) == "for bob"
        # The spoofed frame reached nobody.
        assert decode_text(await next_binary(alice)) == "go"
        assert server.metrics.errors["unauthorized_send"] == 1
        assert "/husky2/chat" not in server.metrics.messages_in


async def test_identity_by_source_address_vs_token(server: RelayServer) -> None:
    async with client(server, source="127.0.0.3") as husky2, \
            client(server, source="127.0.0.9") as anon:
        assert (await next_json(husky2, "welcome"))["identities"] == ["husky2"]
        await anon.send(json.dumps({"token": ALICE_TOKEN}))  # first text frame
        welcome = await next_json(anon, "welcome")
        assert welcome["identities"] == ["alice"]
        assert (await subscribe(anon, "/husky2/.*"))["type"] == "subscribed"
        await husky2.send(string_frame("/husky2/x", "via token frame"))
        assert decode_text(await next_binary(anon)) == "via token frame"


async def test_token_frame_then_binary_keeps_order(server: RelayServer) -> None:
    from fleetctl.wire.control import encode_subscription

    async with client(server, source="127.0.0.9") as anon, \
            client(server, source="127.0.0.2") as robot:
        # Sent back to back, before any answer: the token must be handled first.
        await anon.send(json.dumps({"token": ALICE_TOKEN}))
        await anon.send(encode_subscription("/husky1/.*"))
        assert (await next_json(anon, "subscribed"))["topic_regex"] == "/husky1/.*"
        await robot.send(string_frame("/husky1/a", "x"))
        assert decode_text(await next_binary(anon)) == "x"


async def test_bad_token_and_no_identity_close(server: RelayServer) -> None:
    async with client(server, token="wrong") as ws:
        assert await closed_code(ws) == 4401
    async with client(server, source="127.0.0.9") as ws:
        await ws.send(json.dumps({"token": "wrong"}))
        assert (await next_json(ws, "error"))["code"] == "bad_token"
        assert await closed_code(ws) == 4401
    async with client(server, source="127.0.0.9") as ws:
        await ws.send(string_frame("/a/b"))  # binary before any token
        assert await closed_code(ws) == 4403
    assert server.metrics.closes == {4401: 2, 4403: 1}


async def test_no_identity_times_out(make_server: Callable[..., RelayServer]) -> None:
    async with make_server(limits=ServerLimits(auth_timeout_s=0.2)) as srv, \
            client(srv, source="127.0.0.9") as ws:
        assert await closed_code(ws) == 4403


async def test_tokens_never_stored_or_logged(server: RelayServer,
                                             caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level("DEBUG")
    async with client(server, token=ALICE_TOKEN) as ws:
        await next_json(ws, "welcome")
    async with client(server, token="wrong-secret") as ws:
        await closed_code(ws)
    server_side = "\n".join(
        r.getMessage() for r in caplog.records if not r.name.startswith("websockets.client")
    )
    assert "conn#" in server_side  # the server did log these connections
    assert ALICE_TOKEN not in server_side and "wrong-secret" not in server_side
    assert ALICE_TOKEN not in repr(server.auth.identities)
    assert ALICE_TOKEN not in server.metrics.render()


async def test_fan_out_to_20_consumers(server: RelayServer) -> None:
    consumers = [client(server, token=BOB_TOKEN) for _ in range(20)]
    opened = [await c.__aenter__() for c in consumers]
    try:
        for ws in opened:
            assert (await subscribe(ws, "/husky1/.*"))["type"] == "subscribed"
        async with client(server, source="127.0.0.2") as robot:
            for i in range(10):
                await robot.send(string_frame("/husky1/events", f"e{i}", no_drop=True))
            for ws in opened:
                got = [decode_text(await next_binary(ws)) for _ in range(10)]
                assert got == [f"e{i}" for i in range(10)]
        assert server.metrics.messages_out["/husky1/events"] == 200
    finally:
        for c in consumers:
            await c.__aexit__(None, None, None)


async def test_stalled_consumer_bounded_while_others_keep_up(
    make_server: Callable[..., RelayServer],
) -> None:
    limits = ServerLimits(outbound_queue_bytes=256 * 1024, outbound_no_drop_messages=16)
    async with make_server(limits=limits) as srv, \
            client(srv, token=BOB_TOKEN) as fast, client(srv, token=BOB_TOKEN) as stalled, \
            client(srv, source="127.0.0.2") as robot:
        for ws in (fast, stalled):
            await subscribe(ws, "/husky1/.*")
        stalled.transport.pause_reading()  # a consumer on a dead link
        stalled_peer = max(srv.core.peers.values(),
                           key=lambda p: p.peer_id if "bob" in p.label else -1)
        blob = "x" * 60_000
        received: list[str] = []

        async def consume() -> None:
            while received.count("/husky1/events") < 200:
                msg = await fast.recv()
                if isinstance(msg, bytes):
                    received.append(read_metadata(msg).topic)

        reader = asyncio.create_task(consume())
        for i in range(200):  # ~12 MB: far past socket buffers and the 256 KiB bound
            await robot.send(string_frame(f"/husky1/cam{i % 4}", blob))
            await robot.send(string_frame("/husky1/events", str(i), no_drop=True))
            assert stalled_peer.outbound.queued_bytes <= 256 * 1024 + 61_000
        await asyncio.wait_for(reader, 20)
        # The fast consumer got every no_drop frame; the stalled one dropped, counted.
        assert received.count("/husky1/events") == 200
        await wait_for(lambda: stalled_peer.outbound.dropped_total > 0)
        assert stalled_peer.outbound.drops.get("/husky1/events", 0) > 0
        assert srv.metrics.drops["/husky1/events"] > 0
        stalled.transport.resume_reading()


async def test_bad_input_answered_and_others_unaffected(
    make_server: Callable[..., RelayServer],
) -> None:
    limits = ServerLimits(max_frame_bytes=4096, max_malformed_in_row=5,
                          max_subscriptions_per_connection=3)
    async with make_server(limits=limits) as srv, \
            client(srv, token=ALICE_TOKEN) as victim, client(srv, token=ALICE_TOKEN) as bad, \
            client(srv, source="127.0.0.2") as robot:
        await subscribe(victim, "/husky1/.*")
        good = string_frame("/husky1/a", "ok")
        await bad.send(good[: len(good) // 2])  # truncated
        assert (await next_json(bad, "error"))["code"] == "malformed_frame"
        await bad.send(b"\xff" * 64)  # garbage
        assert (await next_json(bad, "error"))["code"] == "malformed_frame"
        assert (await subscribe(bad, "/husky1/(")) ["code"] == "bad_regex"
        await bad.send(string_frame("/subscriptions", "not a subscription"))
        assert (await next_json(bad, "error"))["code"] == "unknown_type"
        await bad.send("not json")
        assert (await next_json(bad, "error"))["code"] == "malformed_frame"
        for i in range(3):
            assert (await subscribe(bad, f"/x{i}"))["type"] == "subscribed"
        assert (await subscribe(bad, "/x9"))["code"] == "too_many_subscriptions"
        # The victim is still served while the bad client misbehaves.
        await robot.send(good)
        assert decode_text(await next_binary(victim)) == "ok"
        async with client(srv, token=ALICE_TOKEN) as big:
            await big.send(b"\0" * 5000)
            assert await closed_code(big) == 1009
        async with client(srv, token=ALICE_TOKEN) as junk:
            for _ in range(5):
                await junk.send(b"\1" * 16)
            assert await closed_code(junk) == 1007
        async with client(srv, token=ALICE_TOKEN) as flood:
            from fleetctl.wire.control import encode_subscription
            for i in range(3 + 4):
                await flood.send(encode_subscription(f"/f{i}"))
            assert await closed_code(flood) == 4429
        await robot.send(string_frame("/husky1/a", "still"))
        assert decode_text(await next_binary(victim)) == "still"


async def test_http_endpoints_and_forwarded_for(
    make_server: Callable[..., RelayServer],
) -> None:
    import ipaddress

    proxies = (ipaddress.ip_network("127.0.0.5/32"),)
    async with make_server(trusted_proxies=proxies,
                           limits=ServerLimits(auth_timeout_s=0.3)) as srv:
        assert await http_get(srv.port, "/healthz") == (200, "ok\n")
        async with client(srv, source="127.0.0.2") as robot:
            await next_json(robot, "welcome")
            await robot.send(encode_status("husky1", status="ok", is_ok=True,
                                           battery_level=0.5, location="lab"))
            await wait_for(lambda: srv.registry.get("husky1") is not None
                           and srv.registry.get("husky1").status == "ok")  # type: ignore[union-attr]
            status, body = await http_get(srv.port, "/robots")
            robots = json.loads(body)["robots"]
            assert status == 200 and robots[0]["name"] == "husky1" and robots[0]["online"]
            # From a non-loopback identity-less... every test address is loopback, so
            # check the token filter: bob may receive /husky1/.*, so he sees husky1.
            status, body = await http_get(srv.port, "/robots",
                                          {"Authorization": f"Bearer {BOB_TOKEN}"})
            assert [r["name"] for r in json.loads(body)["robots"]] == ["husky1"]
            status, text = await http_get(srv.port, "/robots", {"Authorization": "Bearer bad"})
            assert (status, text) == (
                401, "GET /robots: the Bearer token matches no user or robot of this fleet\n")
            await robot.send(json.dumps({"type": "list_robots"}))
            assert (await next_json(robot, "robots"))["robots"] == []  # cannot receive status
        status, text = await http_get(srv.port, "/metrics")
        assert status == 200 and 'fleetctl_messages_in_total{topic="/husky1/status"} 1' in text
        # X-Forwarded-For from an untrusted peer is ignored ...
        async with client(srv, source="127.0.0.9",
                          additional_headers={"X-Forwarded-For": "127.0.0.2"}) as spoof:
            assert await closed_code(spoof) == 4403
        # ... and believed from a trusted proxy.
        async with client(srv, source="127.0.0.5",
                          additional_headers={"X-Forwarded-For": "127.0.0.2"}) as proxied:
            assert (await next_json(proxied, "welcome"))["identities"] == ["husky1"]


async def test_restart_keeps_registry(make_server: Callable[..., RelayServer]) -> None:
    async with make_server() as srv, client(srv, source="127.0.0.2") as robot:
        await robot.send(encode_status("husky1", status="charging", is_ok=False,
                                       battery_level=0.25, location="dock"))
        await wait_for(lambda: srv.registry.get("husky1") is not None
                       and srv.registry.get("husky1").status == "charging")  # type: ignore[union-attr]
    async with make_server() as again:
        status, body = await http_get(again.port, "/robots")
        assert status == 200
        robot_json, husky2 = json.loads(body)["robots"]  # husky2: the auth map's, unseen
        assert robot_json["name"] == "husky1" and robot_json["status"] == "charging"
        assert husky2["name"] == "husky2" and husky2["never_connected"] is True
        assert robot_json["battery_level"] == 0.25 and robot_json["online"] is False


async def test_robots_reports_an_unknown_battery_as_null(
    make_server: Callable[..., RelayServer],
) -> None:
    """A robot without a battery topic sends -1 (the wire has no null): /robots says null."""
    async with make_server() as srv, client(srv, source="127.0.0.2") as robot:
        await robot.send(encode_status("husky1", status="OK", is_ok=True, battery_level=-1.0))
        await wait_for(lambda: srv.registry.get("husky1") is not None
                       and srv.registry.get("husky1").status == "OK")  # type: ignore[union-attr]
        status, body = await http_get(srv.port, "/robots")
        robot_json = json.loads(body)["robots"][0]
        assert status == 200 and robot_json["name"] == "husky1"
        assert robot_json["battery_level"] is None
