"""The auth map's rules of users: every robot by default, some robots when scoped."""

from __future__ import annotations

from dataclasses import replace
from ipaddress import IPv4Address, IPv4Network

import pytest

from fleetctl.deploy.auth import Rule, identities, scope_regex, user_rules
from fleetctl.deploy.fleet import Fleet, Robot, Role, User
from fleetctl.server.cluster.regexsubjects import regex_subjects
from fleetctl.server.regex import compile_full

FLEET = Fleet(
    name="campus", endpoint=None, subnet=IPv4Network("10.8.0.0/24"),
    server_ip=IPv4Address("10.8.0.1"),
    robots=(Robot("husky1", IPv4Address("10.8.0.2")),
            Robot("jackal2", IPv4Address("10.8.0.3")),
            Robot("husky10", IPv4Address("10.8.0.4")),
            Robot("mapper", IPv4Address("10.8.0.5"), command_topics=())),
)
HUSKY1_COMMANDS = Rule("/husky1/(goal_pose|initialpose)", "send")
JACKAL2_COMMANDS = Rule("/jackal2/(goal_pose|initialpose)", "send")
HUSKY10_COMMANDS = Rule("/husky10/(goal_pose|initialpose)", "send")


def test_unscoped_rules_are_todays() -> None:
    assert user_rules(FLEET, Role.VIEWER) == (Rule("/[^/]+/.*", "receive"),)
    assert user_rules(FLEET, Role.OPERATOR) == (
        Rule("/[^/]+/.*", "receive"), HUSKY1_COMMANDS, JACKAL2_COMMANDS, HUSKY10_COMMANDS)
    assert user_rules(FLEET, Role.ADMIN) == (Rule(".*", "both"),)


def test_a_viewer_scoped_to_one_robot_receives_its_topics_only() -> None:
    assert user_rules(FLEET, Role.VIEWER, ("husky1",)) == (Rule("/husky1/.*", "receive"),)


def test_an_operator_scoped_to_two_robots_commands_those_only() -> None:
    assert user_rules(FLEET, Role.OPERATOR, ("jackal2", "husky1")) == (
        Rule("/(jackal2|husky1)/.*", "receive"), JACKAL2_COMMANDS, HUSKY1_COMMANDS)


def test_a_scoped_robot_without_command_topics_gives_no_send_rule() -> None:
    assert user_rules(FLEET, Role.OPERATOR, ("mapper",)) == (Rule("/mapper/.*", "receive"),)


@pytest.mark.parametrize(
    ("topic", "received"),
    [("/husky1/status", True), ("/jackal2/scan/points", True), ("/husky10/status", False),
     ("/husky1", False), ("/xhusky1/status", False), ("/mapper/status", False),
     ("/husky1|jackal2/status", False)],
)
def test_the_scope_regex_matches_whole_segments_only(topic: str, received: bool) -> None:
    """RE2 full match, as the relay reads it: husky1 is not a prefix of husky10."""
    regex = scope_regex(["husky1", "jackal2"])
    assert regex is not None
    assert compile_full(regex).matches(topic) is received


def test_the_scope_regex_escapes_names() -> None:
    """Validation allows only ROS segments; a name reaching here otherwise still cannot
    widen the rule."""
    assert scope_regex(["a.b", "c"]) == r"/(a\.b|c)/.*"
    assert scope_regex([]) is None


def test_identities_use_each_users_scope() -> None:
    fleet = replace(FLEET, users=(User("all@example.com", Role.VIEWER, "ab" * 32),
                                  User("site@example.com", Role.OPERATOR, "cd" * 32,
                                       ("husky1",))))
    by_name = {i.name: i.rules for i in identities(fleet)}
    assert by_name["all@example.com"] == (Rule("/[^/]+/.*", "receive"),)
    assert by_name["site@example.com"] == (Rule("/husky1/.*", "receive"), HUSKY1_COMMANDS)


def test_a_replica_narrows_its_interest_to_the_scoped_robots() -> None:
    """What a scoped user costs a cluster: a replica's NATS interest follows receive rules
    (docs/scaling.md), and the scope's alternation splits into one subject per robot,
    where every robot's rule is every subject."""
    assert regex_subjects("fleetctl", "/[^/]+/.*").subjects == {"fleetctl.>"}
    derived = regex_subjects("fleetctl", user_rules(FLEET, Role.OPERATOR,
                                                    ("husky1", "jackal2"))[0].topic)
    assert derived.subjects == {"fleetctl.husky1.>", "fleetctl.jackal2.>"}
    assert not derived.unclear
