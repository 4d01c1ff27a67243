"""The authorization map derived from a fleet (docs/design.md section 3).

Robots are identified by their WireGuard source address (a /32 nobody else can send from,
because WireGuard drops packets whose source is not in the sending peer's AllowedIPs);
people by a token whose SHA-256 is stored.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from fleetctl.deploy.fleet import Fleet, Robot, Role, User

Op = Literal["send", "receive", "both"]
IdentityKind = Literal["ip", "cidr", "token_sha256"]

# Everything robots publish: a topic under some robot's namespace.
ROBOT_TOPICS = "/[^/]+/.*"
EVERYTHING = ".*"


@dataclass(frozen=True)
class Rule:
    """Permission *op* on every topic that fully matches the RE2 regex *topic*."""

    topic: str
    op: Op


@dataclass(frozen=True)
class Identity:
    """One auth-map entry: who (``kind`` = ``value``) and what they may do."""

    name: str
    kind: IdentityKind
    value: str
    rules: tuple[Rule, ...]


def command_regex(robot: Robot) -> str | None:
    """Return the regex of robot's command topics, e.g. ``/husky1/(goal_pose|initialpose)``.

    ``None`` when the robot has no command topics. Names and topics are validated to
    letters, digits, ``_`` and ``/``, so they need no regex escaping.
    """
    if not robot.command_topics:
        return None
    alternatives = "|".join(c.topic for c in robot.command_topics)
    return f"/{robot.name}/({alternatives})"


def robot_rules(robot: Robot) -> tuple[Rule, ...]:
    """A robot sends its own namespace and receives its command topics, the topics of its
    ``subscribe`` list (validated topic names: ``[A-Za-z0-9_/]``, a regex matching only
    themselves) and its extras.
    """
    rules = [Rule(f"/{robot.name}/.*", "send")]
    commands = command_regex(robot)
    if commands is not None:
        rules.append(Rule(commands, "receive"))
    rules += [Rule(s.remote_topic, "receive") for s in robot.subscribe]
    rules += [Rule(p, "send") for p in robot.extra_send]
    rules += [Rule(p, "receive") for p in robot.extra_receive]
    return tuple(rules)


def user_rules(fleet: Fleet, role: Role) -> tuple[Rule, ...]:
    """Rules of a role; operators may send every robot's command topics."""
    if role is Role.ADMIN:
        return (Rule(EVERYTHING, "both"),)
    rules = [Rule(ROBOT_TOPICS, "receive")]
    if role is Role.OPERATOR:
        regexes = (command_regex(r) for r in fleet.robots)
        rules += [Rule(rx, "send") for rx in regexes if rx is not None]
    return tuple(rules)


def _user_identity(fleet: Fleet, user: User) -> Identity:
    return Identity(user.email, "token_sha256", user.token_sha256, user_rules(fleet, user.role))


def identities(fleet: Fleet) -> tuple[Identity, ...]:
    """Every identity of the fleet's auth map: robots first, then users."""
    robots = [Identity(r.name, "ip", str(r.ip), robot_rules(r)) for r in fleet.robots]
    return (*robots, *(_user_identity(fleet, u) for u in fleet.users))
