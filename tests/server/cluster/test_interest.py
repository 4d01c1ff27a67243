"""A replica's interest follows subscriptions and their connections' receive rules, as the
subscription map reports them (no NATS needed)."""

from __future__ import annotations

from fleetctl.server.authmap import Identity, Op, Rule
from fleetctl.server.cluster.interest import Interest
from fleetctl.server.permissions import Permissions
from fleetctl.server.regex import compile_full
from fleetctl.server.subscriptions import SubscriptionMap

P = "fleetctl"


def perms(name: str, *receive: str) -> Permissions:
    rules = tuple(Rule(compile_full(t), Op.RECEIVE) for t in receive)
    return Permissions((Identity(name, None, "0" * 64, rules),))


def followed(interest: Interest, calls: list[bool]) -> SubscriptionMap[str]:
    def watch(pattern: str, receive: tuple[str, ...], delta: int) -> None:
        calls.append(interest.follow(pattern, delta, receive))

    return SubscriptionMap(100, watch=watch)


def test_a_broad_subscription_is_narrowed_by_the_receive_rules() -> None:
    interest, calls = Interest(P), []
    subs = followed(interest, calls)
    viewer = perms("viewer", "/husky1/.*")
    subs.subscribe("page", viewer, ".*")
    assert interest.wanted == {"fleetctl.husky1.>"}
    subs.subscribe("page", viewer, "/husky1/status")  # covered: nothing new
    assert interest.wanted == {"fleetctl.husky1.>"}
    subs.subscribe("admin", perms("admin", ".*"), ".*")
    assert interest.wanted == {"fleetctl.>"}
    subs.remove("admin")
    assert interest.wanted == {"fleetctl.husky1.>"}
    subs.unsubscribe("page", ".*")
    assert interest.wanted == {"fleetctl.husky1.status"}
    subs.remove("page")
    assert interest.wanted == frozenset()
    assert interest.counters == {"narrowed": 1, "unchanged": 2, "unclear": 0}


def test_rules_changed_live_change_the_interest() -> None:
    interest, calls = Interest(P), []
    subs = followed(interest, calls)
    subs.subscribe("page", perms("viewer", "/husky1/.*"), ".*")
    subs.subscribe("page", perms("viewer", "/husky1/.*"), "/husky.*")
    assert interest.wanted == {"fleetctl.husky1.>"}
    # An auth reload narrows the rules: the interest follows.
    assert subs.set_permissions("page", perms("viewer", "/husky1/cam/.*")) == []
    assert interest.wanted == {"fleetctl.husky1.cam.>"}
    # ... and widens them.
    subs.set_permissions("page", perms("viewer", "/husky1/.*", "/husky2/.*"))
    assert interest.wanted == {"fleetctl.husky1.>", "fleetctl.husky2.>"}
    subs.set_permissions("page", perms("viewer", "/[^/]+/.*"))
    assert interest.wanted == {"fleetctl.>"}
    # A token frame that adds an identity (new permissions at the next subscribe).
    subs.set_permissions("page", perms("viewer", "/husky1/.*"))
    subs.subscribe("page", perms("viewer+", "/husky1/.*", "/husky3/.*"), "/husky3/x")
    assert interest.wanted == {"fleetctl.husky1.>", "fleetctl.husky3.>"}


def test_a_reload_with_the_same_rules_changes_nothing() -> None:
    interest, calls = Interest(P), []
    subs = followed(interest, calls)
    subs.subscribe("page", perms("viewer", "/husky1/.*"), ".*")
    calls.clear()
    subs.set_permissions("page", perms("viewer", "/husky1/.*"))  # a new pool's object
    assert calls == []
    assert interest.wanted == {"fleetctl.husky1.>"}


def test_a_rules_change_never_lets_a_subject_both_need_go_in_between() -> None:
    interest, calls = Interest(P), []
    subs = followed(interest, calls)
    subs.subscribe("page", perms("viewer", "/husky1/.*"), ".*")
    seen: list[frozenset[str]] = []

    def watch(pattern: str, receive: tuple[str, ...], delta: int) -> None:
        interest.follow(pattern, delta, receive)
        seen.append(interest.wanted)

    subs._watch = watch
    subs.set_permissions("page", perms("viewer", "/husky1/.*", "/husky2/.*"))
    assert all("fleetctl.husky1.>" in wanted for wanted in seen)
    assert seen[-1] == {"fleetctl.husky1.>", "fleetctl.husky2.>"}


def test_subscriptions_refused_by_new_rules_leave_the_interest() -> None:
    interest, calls = Interest(P), []
    subs = followed(interest, calls)
    subs.subscribe("robot", perms("robot", "/husky1/goal_pose"), "/husky1/goal_pose")
    assert interest.wanted == {"fleetctl.husky1.goal_pose"}
    refused = subs.set_permissions("robot", perms("robot", "/husky1/initialpose"))
    assert [pattern for pattern, _ in refused] == ["/husky1/goal_pose"]
    assert interest.wanted == frozenset()


def test_without_rules_the_pattern_alone_decides() -> None:
    interest = Interest(P)
    assert interest.follow(".*", 1)
    assert interest.wanted == {"fleetctl.>"}
    assert not interest.follow(".*", 1, ("/husky1/.*",))  # within fleetctl.>
    assert interest.wanted == {"fleetctl.>"}
    assert interest.follow(".*", -1)
    assert interest.wanted == {"fleetctl.husky1.>"}
    assert interest.follow(".*", -1, ("/husky1/.*",))
    assert interest.wanted == frozenset()


def test_unclear_rules_are_counted() -> None:
    interest = Interest(P)
    interest.follow(".*", 1, ("(?i)/a/.*|/b/.*",))
    assert interest.wanted == {"fleetctl.>"}
    assert interest.counters == {"narrowed": 0, "unchanged": 1, "unclear": 1}
