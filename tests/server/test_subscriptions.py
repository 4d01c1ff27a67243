from __future__ import annotations

import ipaddress

import pytest

from fleetctl.server.permissions import PermissionsPool
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
