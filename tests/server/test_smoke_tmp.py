from __future__ import annotations

from tests.server.conftest import ALICE_TOKEN, client, decode_text, next_binary, next_json, string_frame, subscribe


async def test_smoke(server) -> None:
    async with client(server, token=ALICE_TOKEN) as alice, client(server, source="127.0.0.2") as robot:
        w = await next_json(alice, "welcome")
        print(w)
        print(await next_json(robot, "welcome"))
        print(await subscribe(alice, "/husky1/.*"))
        await robot.send(string_frame("/husky1/chat", "hello"))
        print(decode_text(await next_binary(alice)))
