from __future__ import annotations

import contextlib
import ipaddress
import random

import pytest

from fleetctl.server.permissions import Permissions, PermissionsPool
from fleetctl.server.regex import compile_full
from fleetctl.server.subscriptions import Refusal, SubscriptionMap
from tests.server.conftest import BOB_TOKEN, auth_map

AMAP = auth_map()
POOL = PermissionsPool()
HUSKY = POOL.get(AMAP.match_address(ipaddress.ip_address("127.0.0.2")))
BOB = POOL.get([AMAP.match_token(BOB_TOKEN)])  # type: ignore[list-item]
NOBODY = POOL.get(AMAP.match_address(ipaddress.ip_address("127.0.0.3")))


def test_literal_checked_pattern_filtered_per_delivery() -> None:
    subs: SubscriptionMap[str] = SubscriptionMap(8)
    subs.subscribe("husky", HUSKY, "/husky1/goal_pose")
    with pytest.raises(Refusal) as err:
        subs.subscribe("husky", HUSKY, "/husky1/scan")
    assert err.value.code == "subscription_refused"
    subs.subscribe("bob", BOB, ".*")  # a pattern: accepted, filtered per delivery
    assert subs.receivers("/husky1/goal_pose") == ("husky", "bob")
    assert subs.receivers("/husky1/scan") == ("bob",)
    assert subs.receivers("/husky2/scan") == ()
    with pytest.raises(Refusal) as err:
        subs.subscribe("nobody", NOBODY, ".*")
    assert err.value.code == "subscription_refused"


def test_cache_invalidated_on_change_and_limits() -> None:
    subs: SubscriptionMap[str] = SubscriptionMap(2)
    assert subs.receivers("/husky1/a") == ()
    subs.subscribe("bob", BOB, "/husky1/.*")
    assert subs.receivers("/husky1/a") == ("bob",)
    subs.subscribe("bob", BOB, "/husky1/.*")  # idempotent
    subs.subscribe("bob", BOB, "/husky1/b")
    with pytest.raises(Refusal) as err:
        subs.subscribe("bob", BOB, "/husky1/c")
    assert err.value.code == "too_many_subscriptions"
    assert subs.unsubscribe("bob", "/husky1/.*") and not subs.unsubscribe("bob", "x")
    with pytest.raises(Refusal) as err:  # (quotas are checked before compiling)
        subs.subscribe("bob", BOB, "/husky1/(")
    assert err.value.code == "bad_regex"
    assert subs.receivers("/husky1/a") == ()
    assert subs.receivers("/husky1/b") == ("bob",)
    subs.remove("bob")
    assert subs.receivers("/husky1/b") == () and len(subs) == 0


def _reference(subs: SubscriptionMap[str], perms: dict[str, Permissions],
               topic: str) -> set[str]:
    """Who receives *topic*, asked from scratch (no cache): the answer to match."""
    return {conn for conn in perms if any(compile_full(p).matches(topic)
                                          for p in subs.patterns(conn))
            and perms[conn].may_receive(topic)}


def test_lazy_cache_matches_a_fresh_answer_under_churn() -> None:
    """Pattern changes update cached answers on their topic's next frame; whatever the
    order of changes and frames, the answer is the one asked from scratch."""
    rng = random.Random(7)
    perms: dict[str, Permissions] = {"bob": BOB, "husky": HUSKY, "bob2": BOB}
    patterns = ["/husky1/.*", "/husky1/a.*", "/husky1/(a|b)", "/husky1/goal_pose",
                "/husky1/b", ".*", "/husky2/.*"]
    topics = ["/husky1/a", "/husky1/b", "/husky1/ab", "/husky1/goal_pose", "/husky2/x"]
    subs: SubscriptionMap[str] = SubscriptionMap(16)
    for _ in range(3000):
        conn = rng.choice(list(perms))
        pattern = rng.choice(patterns)
        action = rng.random()
        if action < 0.35:
            with contextlib.suppress(Refusal):  # e.g. a literal husky may not receive
                subs.subscribe(conn, perms[conn], pattern)
        elif action < 0.7:
            subs.unsubscribe(conn, pattern)
        elif action < 0.75:
            subs.remove(conn)
        else:
            topic = rng.choice(topics)
            assert set(subs.receivers(topic)) == _reference(subs, perms, topic), topic
            assert len(set(subs.receivers(topic))) == len(subs.receivers(topic))


def test_forgotten_changes_recompute_whole(monkeypatch: pytest.MonkeyPatch) -> None:
    """Past MAX_PENDING_CHANGES changed connections an old answer is asked again whole."""
    import fleetctl.server.subscriptions as module

    monkeypatch.setattr(module, "MAX_PENDING_CHANGES", 2)
    subs: SubscriptionMap[str] = SubscriptionMap(8)
    assert subs.receivers("/husky1/a") == ()
    for conn in ("c1", "c2", "c3", "c4"):  # c1 and c2 are forgotten as changes
        subs.subscribe(conn, BOB, "/husky1/.*")
    assert set(subs.receivers("/husky1/a")) == {"c1", "c2", "c3", "c4"}
    subs.unsubscribe("c1", "/husky1/.*")
    subs.subscribe("c5", BOB, "/husky1/a")  # a literal: the answer changes at once
    assert set(subs.receivers("/husky1/a")) == {"c2", "c3", "c4", "c5"}


class _Calls:
    """Counts the regex calls of the subscription map: a pattern's own
    (``FullMatch``) and a connection's joined ones (``AnyOf``, which may call the first)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        from fleetctl.server import regex

        self.by: dict[str, int] = {"FullMatch": 0, "AnyOf": 0}
        for cls in (regex.FullMatch, regex.AnyOf):
            original = cls.matches

            def counted(obj: object, topic: str, _original: object = original,
                        _name: str = cls.__name__) -> bool:
                self.by[_name] += 1
                return _original(obj, topic)  # type: ignore[operator,no-any-return]

            monkeypatch.setattr(cls, "matches", counted)


def test_pattern_change_costs_no_regex_call_per_cached_topic(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A subscribe/unsubscribe of a pattern with 16,000 topics cached makes no RE2 call;
    a frame afterwards costs one call per changed connection on its own topic."""
    subs: SubscriptionMap[str] = SubscriptionMap(8)
    subs.subscribe("viewer", BOB, "/husky1/t1.*")
    topics = [f"/husky1/t{i}" for i in range(16000)]
    for topic in topics:
        subs.receivers(topic)
        BOB.may_receive(topic)  # (the receive rules' answers are cached per topic too)
    calls = _Calls(monkeypatch)
    for _ in range(50):
        subs.subscribe("churner", BOB, "/husky1/t2.*")
        subs.unsubscribe("churner", "/husky1/t2.*")
    subs.subscribe("churner", BOB, "/husky1/t2.*")
    assert calls.by == {"FullMatch": 0, "AnyOf": 0}
    assert set(subs.receivers("/husky1/t25")) == {"churner"}
    assert set(subs.receivers("/husky1/t150")) == {"viewer"}
    # The churner asked once on each topic (its one pattern), the viewer kept its place.
    assert calls.by == {"FullMatch": 2, "AnyOf": 2}
    assert subs.receivers("/husky1/t25") == ("churner",)
    assert calls.by == {"FullMatch": 2, "AnyOf": 2}  # cached again: no call


def _newly_matched_reference(conn_patterns: list[str], perms: Permissions, new: list[str],
                             stored: list[str]) -> list[str]:
    """What new subscriptions *new* start delivering, asked from scratch: every stored
    topic in order, each matched against every subscription in turn."""
    others = [compile_full(p) for p in conn_patterns if p not in new]
    added = [compile_full(p) for p in new]
    return [t for t in stored if any(n.matches(t) for n in added) and perms.may_receive(t)
            and not any(o.matches(t) for o in others)]


def test_newly_matched_equals_a_fresh_answer_under_churn() -> None:
    """The index narrows the topics looked at and the others are asked in one matcher
    (reused while they do not change); the topics found, for one new subscription or a
    resumed session's several, are the ones a scan of every stored topic finds, in the
    store's order."""
    from fleetctl.server.topicindex import TopicIndex

    rng = random.Random(13)
    patterns = ["/husky1/.*", "/husky1/a.*", "/husky1/(a|b)", "/husky1/goal_pose", "/husky1/b",
                ".*", "/husky2/.*", ".*b", "(?i)/HUSKY1/A.*", "/husky[12]/.*x", "/husky1/a"]
    names = ["/husky1/a", "/husky1/b", "/husky1/ab", "/husky1/goal_pose", "/husky2/x",
             "/husky1/ax", "/HUSKY1/A", "/husky3/b", "/husky1/ä", "/husky1/"]
    perms: dict[str, Permissions] = {"bob": BOB, "husky": HUSKY}
    subs: SubscriptionMap[str] = SubscriptionMap(16)
    index = TopicIndex()
    found_any = 0
    for _ in range(4000):
        conn = rng.choice(list(perms))
        action = rng.random()
        if action < 0.3:
            index.add(rng.choice(names))
        elif action < 0.4:
            index.discard(rng.choice(names))
        elif action < 0.65:
            subs.unsubscribe(conn, rng.choice(patterns))
        else:
            added = []
            for pattern in rng.sample(patterns, 1 if action < 0.85 else rng.randint(2, 4)):
                with contextlib.suppress(Refusal):  # e.g. a literal husky may not receive
                    if subs.subscribe(conn, perms[conn], pattern):
                        added.append(pattern)
            got = subs.newly_matched(conn, added, index.candidates)
            want = _newly_matched_reference(subs.patterns(conn), perms[conn], added, list(index))
            assert got.topics == want, (conn, added, subs.patterns(conn), list(index))
            found_any += bool(got.topics)
    assert found_any > 20


def test_newly_matched_looks_only_at_the_topics_a_prefix_may_match(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """With 4,096 topics stored, a prefix pattern costs the topics in its range, a
    literal one lookup; a pattern RE2 cannot bound is asked of every topic, and its work
    says so. Others whose range cannot meet the new pattern's are not asked."""
    from fleetctl.server.topicindex import TopicIndex

    index = TopicIndex()
    for i in range(4096):
        index.add(f"/husky1/r{i // 32}/t{i}")
    bob = Permissions(BOB.identities)  # its own cache (other tests fill BOB's)
    for topic in index:
        bob.may_receive(topic)  # (the receive rules' answers are cached per topic)
    subs: SubscriptionMap[str] = SubscriptionMap(8)
    subs.subscribe("bob", bob, "/husky1/r9/.*")  # another range: never asked below
    calls = _Calls(monkeypatch)
    subs.subscribe("bob", bob, "/husky1/r7/.*")
    found = subs.newly_matched("bob", ["/husky1/r7/.*"], index.candidates)
    assert found.topics == [f"/husky1/r7/t{i}" for i in range(224, 256)]
    assert found.work == 64 and calls.by == {"FullMatch": 32, "AnyOf": 0}
    subs.subscribe("bob", bob, "/husky1/r8/t260")
    found = subs.newly_matched("bob", ["/husky1/r8/t260"], index.candidates)
    assert found.topics == ["/husky1/r8/t260"] and found.work == 2
    subs.subscribe("bob", bob, ".*scan|.*t4095")
    found = subs.newly_matched("bob", [".*scan|.*t4095"], index.candidates)
    joined = sum(compile_full(p).cost for p in ("/husky1/r9/.*", "/husky1/r7/.*")) // 8
    assert found.topics == ["/husky1/r127/t4095"] and found.work == 4096 + 1 + joined


def test_others_joined_once_while_they_do_not_change() -> None:
    """A churn of one pattern beside held ones joins the held ones once (the work counts
    the join the first time only)."""
    from fleetctl.server.topicindex import TopicIndex

    index = TopicIndex()
    for i in range(100):
        index.add(f"/husky1/t{i}")
    subs: SubscriptionMap[str] = SubscriptionMap(8)
    subs.subscribe("bob", BOB, "/husky1/t1.*")
    subs.subscribe("bob", BOB, "/husky1/t2.*")
    works = []
    for _ in range(3):
        subs.subscribe("bob", BOB, "/husky1/.*")
        found = subs.newly_matched("bob", ["/husky1/.*"], index.candidates)
        assert len(found.topics) == 100 - 22  # t1, t10-t19, t2, t20-t29 came before
        works.append(found.work)
        subs.unsubscribe("bob", "/husky1/.*")
    joined = (compile_full("/husky1/t1.*").cost + compile_full("/husky1/t2.*").cost) // 8
    assert works == [200 + joined, 200, 200]
