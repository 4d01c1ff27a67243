"""The --robots checks of add-user/set-user, and removing a robot users are scoped to."""

from __future__ import annotations

from dataclasses import replace
from ipaddress import IPv4Address, IPv4Network
from pathlib import Path

import pytest

from fleetctl.deploy.fleet import Fleet, Robot, Role, User
from fleetctl.deploy.userscope import check_scope, scope_text, without_robot
from fleetctl.errors import ConfigError, ConflictError, ExitCode, FleetError

FLEET_DIR = Path("/f")
FLEET = Fleet(
    name="campus", endpoint=None, subnet=IPv4Network("10.8.0.0/24"),
    server_ip=IPv4Address("10.8.0.1"),
    robots=(Robot("husky1", IPv4Address("10.8.0.2")), Robot("jackal2", IPv4Address("10.8.0.3"))),
)


@pytest.mark.parametrize(("role", "robots", "error", "code", "message"), [
    (Role.ADMIN, ("husky1",), FleetError, ExitCode.USAGE,
     "--robots: an admin may use every robot and cannot be scoped to some (make the user a "
     "viewer or an operator)"),
    (Role.VIEWER, (), FleetError, ExitCode.USAGE,
     "--robots: name at least one robot (or --all-robots for every robot)"),
    (Role.OPERATOR, ("husky1", "jackal2", "husky1"), FleetError, ExitCode.USAGE,
     "--robots: robot 'husky1' is given twice"),
    (Role.VIEWER, ("husky9", "husky1", "Jackal2"), ConfigError, ExitCode.CONFIG,
     "--robots: no robot 'husky9', 'Jackal2' in /f/fleet.yaml (its robots: husky1, jackal2)"),
])
def test_check_scope_refusals(role: Role, robots: tuple[str, ...], error: type[FleetError],
                              code: ExitCode, message: str) -> None:
    with pytest.raises(error) as info:
        check_scope(FLEET, FLEET_DIR, role, robots)
    assert (info.value.exit_code, str(info.value)) == (code, message)


def test_check_scope_accepts_robots_of_the_fleet() -> None:
    check_scope(FLEET, FLEET_DIR, Role.OPERATOR, ("jackal2", "husky1"))


def test_removing_a_robot_drops_it_from_scopes_and_says_so() -> None:
    users = (User("all@example.com", Role.VIEWER, "ab" * 32),
             User("two@example.com", Role.OPERATOR, "cd" * 32, ("husky1", "jackal2")),
             User("other@example.com", Role.VIEWER, "ef" * 32, ("jackal2",)))
    left, notes = without_robot(replace(FLEET, users=users), FLEET_DIR, "husky1")
    assert [u.robots for u in left] == [None, ("jackal2",), ("jackal2",)]
    assert left[1].token_sha256 == "cd" * 32
    assert notes == ("user 'two@example.com' is scoped to jackal2 now (robot 'husky1' left "
                     "their robots in /f/fleet.yaml)",)
    _, preview = without_robot(replace(FLEET, users=users), FLEET_DIR, "husky1", dry_run=True)
    assert preview[0].startswith("user 'two@example.com' would be scoped to jackal2 now")


def test_removing_the_only_robot_of_a_user_is_refused() -> None:
    users = (User("site@example.com", Role.VIEWER, "ab" * 32, ("husky1",)),)
    with pytest.raises(ConflictError) as info:
        without_robot(replace(FLEET, users=users), FLEET_DIR, "husky1")
    assert str(info.value) == (
        "robot 'husky1' is the only robot of user 'site@example.com' (fleet.yaml "
        "users[].robots): give them another first (`fleetctl set-user site@example.com "
        "--robots NAME`, or --all-robots) or remove them (`fleetctl remove-user "
        "site@example.com`); nothing was changed")


def test_scope_text() -> None:
    assert scope_text(None) == "every robot"
    assert scope_text(("husky1", "jackal2")) == "husky1, jackal2"
