"""Subscription patterns whose RE2 programs are large for their text: each is bounded in
memory and counted by its program in the pattern quotas (docs/security.md, "Limits")."""

from __future__ import annotations

import asyncio

import pytest

from fleetctl.server import relay
from fleetctl.server.app import RelayServer
from fleetctl.server.regex import (
    QUOTA_BYTES_PER_INSTRUCTION,
    AnyOf,
    FullMatch,
    compile_full,
)
from tests.server.conftest import ALICE_TOKEN, client, next_binary, next_json, subscribe
from tests.support import decode_text, string_frame


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


async def test_a_new_topic_costs_one_regex_call_per_connection(
    server: RelayServer, monkeypatch: pytest.MonkeyPatch,
) -> None:
    # google-re2's binding costs 6-10 us a call: a topic matched against each of 2,400
    # pattern subscriptions in turn cost 17-52 ms, and a sender may use a new topic in
    # every frame.
    calls = [0]
    real = FullMatch.matches
    ours = {f"/husky1/(x{i}|y)[0-9]+" for i in range(60)} | {"/husky1/lit", "/husky1/t3"}

    def counted(self: FullMatch, topic: str) -> bool:
        calls[0] += self.pattern in ours  # the subscriptions, not the identities' rules
        return real(self, topic)

    async with client(server, token=ALICE_TOKEN) as viewer, \
            client(server, source="127.0.0.2") as robot:
        await next_json(viewer, "welcome")
        await next_json(robot, "welcome")
        for pattern in sorted(ours - {"/husky1/t3"}):
            assert (await subscribe(viewer, pattern))["type"] == "subscribed"
        monkeypatch.setattr(FullMatch, "matches", counted)
        for i in range(20):  # new topics, none of them for the viewer
            await robot.send(string_frame(f"/husky1/t{i}", "x"))
        await robot.send(string_frame("/husky1/x7123", "for the viewer"))
        await robot.send(string_frame("/husky1/lit", "literal"))
        assert decode_text(await next_binary(viewer)) == "for the viewer"
        assert decode_text(await next_binary(viewer)) == "literal"
        assert calls[0] == 0  # one joined regex per connection, not 61 calls a topic
        # A subscription changes the join; a literal one touches one cached topic only.
        assert (await subscribe(viewer, "/husky1/t3"))["type"] == "subscribed"
        assert calls[0] == 1
        await robot.send(string_frame("/husky1/t3", "now yours"))
        assert decode_text(await next_binary(viewer)) == "now yours"


def test_joined_patterns_answer_as_each_pattern_would() -> None:
    # Flags scoped to their group, anchors, an open \Q (not joinable: tried one by one),
    # literals, non-ASCII text and a lone surrogate.
    patterns = [compile_full(p) for p in (r"\Qa.b", "(?i)/HUSKY1/.*", "/a/b", "x|y", "(a)(b)",
                                          r"/p/\d+", ".*z", "/é/.*", "(?s).", "^/a$")]
    topics = ["a.b", "/husky1/scan", "/a/b", "x", "y", "ab", "/p/12", "/é/x", "\n", "/a",
              "\ud800", "", "zz"]
    for n in range(1, len(patterns) + 1):
        for start in range(len(patterns)):
            chosen = (patterns * 2)[start:start + n]
            joined = AnyOf(chosen)
            for topic in topics:
                assert joined.matches(topic) == any(p.matches(topic) for p in chosen), \
                    (topic, [p.pattern for p in chosen])


async def test_new_topics_are_rate_limited_per_identity_set(
    server: RelayServer, monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A sender inventing a topic per frame cost ~10x a frame each (a regex call per
    # subscribed connection, new permission, metrics and catalog entries). Past the burst
    # its frames wait, unread, and are taken at the rate, in order: none is dropped (a
    # pong after a dropped no_drop frame would lose it, test_pongs_after_rate_limits).
    monkeypatch.setattr(relay, "NEW_TOPICS_BURST", 20)
    monkeypatch.setattr(relay, "NEW_TOPICS_PER_S", 50.0)
    async with client(server, token=ALICE_TOKEN) as viewer, \
            client(server, source="127.0.0.2") as robot:
        await next_json(viewer, "welcome")
        await next_json(robot, "welcome")
        assert (await subscribe(viewer, "/husky1/.*"))["type"] == "subscribed"
        loop = asyncio.get_running_loop()
        started = loop.time()
        for i in range(50):
            await robot.send(string_frame(f"/husky1/t{i}", f"{i}"))
        await robot.send(string_frame("/husky1/t3", "known topic"))  # waits behind them
        error = await next_json(robot, "error")
        assert error["code"] == "rate_limited" and error["topic"] == "/husky1/t20"
        got = [decode_text(await next_binary(viewer)) for _ in range(51)]
        assert got == [str(i) for i in range(50)] + ["known topic"]
        # 30 past the burst at 50/s: the relay took them no faster than the rate.
        assert loop.time() - started >= 30 / 50.0
        assert "new_topic_rate" not in server.metrics.errors  # nothing dropped
        assert server.metrics.reads_paused["new_topic_rate"] >= 1
