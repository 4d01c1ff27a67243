"""Subscription patterns whose RE2 programs are large for their text: each is bounded in
memory and counted by its program in the pattern quotas (docs/security.md, "Limits")."""

from __future__ import annotations

from fleetctl.server.app import RelayServer
from fleetctl.server.regex import QUOTA_BYTES_PER_INSTRUCTION, compile_full
from tests.server.conftest import ALICE_TOKEN, client, next_json, subscribe


async def test_a_pattern_over_the_regex_memory_budget_is_a_bad_regex(
    server: RelayServer,
) -> None:
    async with client(server, token=ALICE_TOKEN) as ws:
        await next_json(ws, "welcome")
        # 21 characters, 0.8 MB and 11-20 ms of compiling each with RE2's default budget.
        answer = await subscribe(ws, ".{1000}.{1000}.{1000}")
        assert answer["type"] == "error" and answer["code"] == "bad_regex"
        assert "too large" in answer["message"]
        assert (await subscribe(ws, "/husky1/.*"))["type"] == "subscribed"


async def test_short_patterns_with_large_programs_count_by_their_program(
    server: RelayServer,
) -> None:
    dear = ".{99}.{99}.{99}.{99}.{99}x%d"  # 28 characters, ~4,000 RE2 instructions
    cost = compile_full(dear % 0).cost
    assert cost >= QUOTA_BYTES_PER_INSTRUCTION * 3000
    fits = server.config.limits.max_pattern_bytes_per_connection // cost
    async with client(server, token=ALICE_TOKEN) as ws:
        await next_json(ws, "welcome")
        answers = [await subscribe(ws, dear % i) for i in range(fits + 1)]
        assert [a["type"] for a in answers] == ["subscribed"] * fits + ["error"]
        assert answers[-1]["code"] == "too_many_subscriptions"
        # Ordinary subscriptions still fit beside them: 200 topics and a few patterns.
        await subscribe(ws, dear % 0)  # idempotent: not charged twice
        peer = next(iter(server.core.peers.values()))
        assert server.core.subs.pattern_bytes(peer) == fits * cost
    async with client(server, token=ALICE_TOKEN) as ws:
        await next_json(ws, "welcome")
        for i in range(200):
            assert (await subscribe(ws, f"/husky{i}/scan"))["type"] == "subscribed"
        for pattern in ("/husky1/.*", ".*/(scan|odom|tf)", "(?i)/HUSKY[0-9]+/map"):
            assert (await subscribe(ws, pattern))["type"] == "subscribed"
