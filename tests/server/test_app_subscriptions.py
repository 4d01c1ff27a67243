"""A pattern subscribe/unsubscribe with many topics cached, through a real relay: the
receiver cache catches up lazily, and a subscriber still gets every frame published
after its ``subscribed`` and none after its ``unsubscribed``."""

from __future__ import annotations

from typing import Any

from fleetctl.server.app import RelayServer
from fleetctl.wire.control import encode_subscription
from tests.server.conftest import ALICE_TOKEN, client, next_binary, next_json, subscribe
from tests.support import decode_text, string_frame

CACHED = 3000  # topics routed before the subscriptions change (within the new-topic burst)


async def next_news(ws: Any) -> str:
    """The text of the next frame that is not one of the frames filling the cache."""
    while (text := decode_text(await next_binary(ws))) == "fill":
        pass
    return text


async def test_pattern_changes_with_many_cached_topics(server: RelayServer) -> None:
    async with client(server, source="127.0.0.2") as robot, \
            client(server, token=ALICE_TOKEN) as viewer, \
            client(server, token=ALICE_TOKEN) as steady:
        await next_json(robot, "welcome")
        assert (await subscribe(steady, "/husky1/t2.*"))["type"] == "subscribed"
        assert (await subscribe(viewer, "/husky1/done"))["type"] == "subscribed"
        for i in range(CACHED):
            await robot.send(string_frame(f"/husky1/t{i}", "fill"))
        await robot.send(string_frame("/husky1/done", "filled", no_drop=True))
        assert decode_text(await next_binary(viewer)) == "filled"  # all routed: in order
        assert server.core.subs.routes(f"/husky1/t{CACHED - 1}")

        for _ in range(3):  # pattern churn on the cached topics
            assert (await subscribe(viewer, "/husky1/t1.*"))["type"] == "subscribed"
            await viewer.send(encode_subscription("/husky1/t1.*", False))
            await next_json(viewer, "unsubscribed")
        assert (await subscribe(viewer, "/husky1/t1.*"))["type"] == "subscribed"
        for topic in ("/husky1/t1500", "/husky1/t7", "/husky1/t2500", "/husky1/done"):
            await robot.send(string_frame(topic, topic, no_drop=True))
        assert [decode_text(await next_binary(viewer)) for _ in range(2)] == [
            "/husky1/t1500", "/husky1/done"]
        assert await next_news(steady) == "/husky1/t2500"

        await viewer.send(encode_subscription("/husky1/t1.*", False))
        await next_json(viewer, "unsubscribed")
        for topic in ("/husky1/t1500", "/husky1/t2501", "/husky1/done"):
            await robot.send(string_frame(topic, topic, no_drop=True))
        assert decode_text(await next_binary(viewer)) == "/husky1/done"  # t1500 not
        assert await next_news(steady) == "/husky1/t2501"
