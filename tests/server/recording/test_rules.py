"""Which frames are recorded: topic RE2 and sender identities, cached per identity set."""

from __future__ import annotations

from fleetctl.server.permissions import PermissionsPool
from fleetctl.server.recording.config import RecordingRule
from fleetctl.server.recording.rules import RecordingRules
from tests.server.conftest import auth_map


def test_topic_and_identity_rules() -> None:
    pool = PermissionsPool()
    by_name = {i.name: i for i in auth_map().identities}
    husky1 = pool.get([by_name["husky1"]])
    alice = pool.get([by_name["alice"]])
    both = pool.get([by_name["husky1"], by_name["alice"]])
    rules = RecordingRules((RecordingRule("/husky1/.*", ("husky1",)),
                            RecordingRule("/.*/status")))
    assert rules.matches("/husky1/scan", husky1)
    assert not rules.matches("/husky1/scan", alice)  # not husky1's data
    assert rules.matches("/husky1/scan", both)
    assert rules.matches("/husky2/status", alice)  # any sender
    assert not rules.matches("/husky2/status/x", alice)  # full match
    assert not rules.matches("/husky1/scanner", alice)
    # Cached: the same answers again, from the cache.
    assert rules.matches("/husky1/scan", husky1) and not rules.matches("/husky1/scan", alice)
    assert len(rules._cache) == 6
