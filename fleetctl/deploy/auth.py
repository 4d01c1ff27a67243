"""The authorization map derived from a fleet (docs/design.md section 3).

Robots are identified by their WireGuard source address (a /32 nobody else can send from,
because WireGuard drops packets whose source is not in the sending peer's AllowedIPs);
people by a token whose SHA-256 is stored.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
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


def scope_regex(names: Iterable[str]) -> str | None:
    """Return the regex of every topic of the robots *names*: ``/husky1/.*`` for one,
    ``/(husky1|jackal2)/.*`` for more; ``None`` for none.

    One alternation rather than one rule per robot: a relay replica derives its NATS
    subjects from it alternative by alternative (docs/scaling.md, "Interest narrowed by
    receive rules"), up to 16 robots; past that the rule still holds, only the replica's
    interest is the broad one. Names are validated ROS segments, escaped all the same so
    that a name can never widen the rule.
    """
    escaped = [re.escape(n) for n in names]
    if not escaped:
        return None
    return f"/{escaped[0]}/.*" if len(escaped) == 1 else f"/({'|'.join(escaped)})/.*"


def user_rules(fleet: Fleet, role: Role, robots: tuple[str, ...] | None = None
               ) -> tuple[Rule, ...]:
    """Rules of a role: viewers receive robots' topics, operators also send their command
    topics, admins send and receive everything.

    Args:
        fleet: the fleet (its robots' command topics).
        role: the user's role.
        robots: the user's scope (:attr:`~fleetctl.deploy.fleet.User.robots`): those
            robots only, in this order; ``None``: every robot (an admin's is ignored:
            validation refuses it).
    """
    if role is Role.ADMIN:
        return (Rule(EVERYTHING, "both"),)
    scoped = fleet.robots if robots is None else [
        r for r in (fleet.robot(n) for n in robots) if r is not None]
    receive = ROBOT_TOPICS if robots is None else scope_regex(r.name for r in scoped)
    rules = [] if receive is None else [Rule(receive, "receive")]
    if role is Role.OPERATOR:
        regexes = (command_regex(r) for r in scoped)
        rules += [Rule(rx, "send") for rx in regexes if rx is not None]
    return tuple(rules)


def _user_identity(fleet: Fleet, user: User) -> Identity:
    return Identity(user.email, "token_sha256", user.token_sha256,
                    user_rules(fleet, user.role, user.robots))


def identities(fleet: Fleet) -> tuple[Identity, ...]:
    """Every identity of the fleet's auth map: robots first, then users."""
    robots = [Identity(r.name, "ip", str(r.ip), robot_rules(r)) for r in fleet.robots]
    return (*robots, *(_user_identity(fleet, u) for u in fleet.users))
