"""Users scoped to some robots (``fleetctl add-user/set-user --robots``, fleet.yaml
``users[].robots``): the command's names checked against the fleet, and what removing a
robot does to the scopes that name it (docs/operator.md, "Users scoped to some robots").

fleet.yaml itself is validated by :func:`fleetctl.deploy.fleet.check_user_robots`; here
the same rules are said in terms of the command's options, with the exit code each
mistake has.
"""

from __future__ import annotations

import shlex
from dataclasses import replace
from pathlib import Path

from fleetctl.deploy.fleet import Fleet, Role, User, fleet_file
from fleetctl.errors import ConfigError, ConflictError, ExitCode, FleetError


def scope_text(robots: tuple[str, ...] | None) -> str:
    """A scope as people read it: ``husky1, jackal2``, or ``every robot`` for ``None``."""
    return "every robot" if robots is None else ", ".join(robots)


def check_scope(fleet: Fleet, fleet_dir: Path, role: Role, robots: tuple[str, ...]) -> None:
    """Refuse a ``--robots`` scope the user cannot have.

    Raises:
        FleetError: (usage, exit 2) *role* is admin, *robots* is empty or names a robot
            twice.
        ConfigError: (exit 3) a name is not a robot of the fleet; the message names it
            and the fleet's robots.
    """
    if role is Role.ADMIN:
        raise FleetError("--robots: an admin may use every robot and cannot be scoped to "
                         "some (make the user a viewer or an operator)",
                         exit_code=ExitCode.USAGE)
    if not robots:
        raise FleetError("--robots: name at least one robot (or --all-robots for every "
                         "robot)", exit_code=ExitCode.USAGE)
    if twice := next((n for i, n in enumerate(robots) if n in robots[:i]), None):
        raise FleetError(f"--robots: robot {twice!r} is given twice",
                         exit_code=ExitCode.USAGE)
    unknown = [n for n in robots if fleet.robot(n) is None]
    if unknown:
        names = ", ".join(repr(n) for n in unknown)
        known = ", ".join(r.name for r in fleet.robots) or "none yet"
        raise ConfigError(f"--robots: no robot {names} in {fleet_file(fleet_dir)} (its "
                          f"robots: {known})")


def without_robot(fleet: Fleet, fleet_dir: Path, name: str, *, dry_run: bool = False
                  ) -> tuple[tuple[User, ...], tuple[str, ...]]:
    """The fleet's users once robot *name* is removed, and one note per user whose scope
    named it.

    A user whose only robot it is stops the removal: an empty scope would be a token that
    shows nothing, and fleet.yaml refuses ``robots: []`` (it reads too easily as "no
    restriction").

    Raises:
        ConflictError: *name* is the only robot of some users; the message names them and
            the two ways out.
    """
    stranded = [u.email for u in fleet.users if u.robots == (name,)]
    if stranded:
        who = ("user " if len(stranded) == 1 else "users ") + ", ".join(map(repr, stranded))
        first = shlex.quote(stranded[0])
        raise ConflictError(
            f"robot {name!r} is the only robot of {who} (fleet.yaml users[].robots): "
            f"give them another first (`fleetctl set-user {first} --robots NAME`, or "
            f"--all-robots) or remove them (`fleetctl remove-user {first}`); nothing was "
            "changed")
    users: list[User] = []
    notes: list[str] = []
    for user in fleet.users:
        if user.robots is None or name not in user.robots:
            users.append(user)
            continue
        left = tuple(n for n in user.robots if n != name)
        users.append(replace(user, robots=left))
        verb = "would be" if dry_run else "is"
        notes.append(f"user {user.email!r} {verb} scoped to {scope_text(left)} now (robot "
                     f"{name!r} left their robots in {fleet_file(fleet_dir)})")
    return tuple(users), tuple(notes)
