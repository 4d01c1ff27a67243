from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Any

import pytest

from fleetctl.errors import ConfigError
from fleetctl.server.authmap import load_auth_map, parse_auth_map
from fleetctl.server.permissions import PermissionsPool
from tests.server.conftest import ALICE_TOKEN, AUTH, auth_map

P = Path("auth.yaml")


def ip(text: str) -> Any:
    return ipaddress.ip_address(text)


def test_match_by_ip_cidr_and_token() -> None:
    amap = parse_auth_map(
        {"identities": [
            {"name": "a", "ip": "10.8.0.2", "rules": []},
            {"name": "net", "cidr": "10.8.0.0/24", "rules": []},
            *AUTH["identities"][2:3],
        ]}, P)
    assert [i.name for i in amap.match_address(ip("10.8.0.2"))] == ["a", "net"]
    assert [i.name for i in amap.match_address(ip("10.8.0.9"))] == ["net"]
    assert amap.match_address(ip("10.9.0.1")) == []
    assert amap.match_address(ip("::1")) == []
    found = amap.match_token(ALICE_TOKEN)
    assert found is not None and found.name == "alice"
    assert amap.match_token("wrong") is None
    assert ALICE_TOKEN not in repr(found)


def test_full_match_permissions_union() -> None:
    amap = auth_map()
    pool = PermissionsPool()
    husky = pool.get(amap.match_address(ip("127.0.0.2")))
    assert husky.may_send("/husky1/scan")
    assert not husky.may_send("/husky1")  # full match: "/husky1/.*" needs the slash
    assert not husky.may_send("/husky2/scan")
    assert not husky.may_send("x/husky1/scan")  # anchored at the start too
    assert husky.may_receive("/husky1/goal_pose")
    assert not husky.may_receive("/husky1/goal_pose_extra")
    assert not husky.may_receive("/husky1/scan")
    both = pool.get([*amap.match_address(ip("127.0.0.2")), amap.match_token(ALICE_TOKEN)])
    assert both.may_receive("/husky1/scan") and both.may_send("/anything")
    assert pool.get(amap.match_address(ip("127.0.0.2"))) is husky  # shared, cached


def test_nothing_allowed_by_default() -> None:
    perms = PermissionsPool().get([])
    assert not perms.may_send("/a") and not perms.may_receive("/a") and not perms.any_receive


@pytest.mark.parametrize(
    ("identity", "message"),
    [
        ({"name": "x", "ip": "1.2.3.4", "rules": [{"topic": "a(b", "op": "send"}]},
         "identity 'x': rules[0]: field 'topic'"),
        ({"name": "x", "ip": "1.2.3.4", "rules": [{"topic": "a", "op": "write"}]},
         "identity 'x': rules[0]: field 'op'"),
        ({"name": "x", "ip": "1.2.3.4", "cidr": "1.2.3.0/24"}, "exactly one"),
        ({"name": "x", "ip": "1.2.3.400"}, "field 'ip'"),
        ({"name": "x", "token_sha256": "abc"}, "64 hex"),
        ({"ip": "1.2.3.4"}, "field 'name'"),
        # a lone surrogate ("\ud800" in YAML): RE2 raised UnicodeEncodeError
        ({"name": "x", "ip": "1.2.3.4", "rules": [{"topic": "/r1/\ud800", "op": "send"}]},
         "identity 'x': rules[0]: field 'topic': bad RE2 regex '/r1/\\ud800': not UTF-8 text"),
    ],
)
def test_bad_auth_map_is_config_error(identity: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_auth_map({"identities": [identity]}, P)
    assert "auth.yaml" in str(err.value) and message in str(err.value)


def test_duplicate_names_and_file_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="twice"):
        parse_auth_map({"identities": [{"name": "a", "ip": "1.1.1.1"},
                                       {"name": "a", "ip": "1.1.1.2"}]}, P)
    with pytest.raises(ConfigError, match="cannot read"):
        load_auth_map(tmp_path / "missing.yaml")
    bad = tmp_path / "auth.yaml"
    bad.write_text("identities: [")
    with pytest.raises(ConfigError, match="YAML"):
        load_auth_map(bad)


def test_a_surrogate_topic_matches_no_rule() -> None:
    # Foxglove's JSON can name "/husky1/\ud800" (fuzzing): no topic on the wire can be it.
    perms = PermissionsPool().get(list(auth_map().identities))
    assert not perms.may_send("/husky1/\ud800") and not perms.may_receive("\udc00")
