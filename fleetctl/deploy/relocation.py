"""Whose deployment a fleet directory's recorded state is, once the directory was moved or
copied (docs/deploy.md, "Moved and copied fleet directories").

``up`` records its options, compose project included, and the resolved fleet directory it
ran in (``FLEET/.compose/state.json``). The default project is made from the directory's
path (:func:`~fleetctl.deploy.compose.project_name`), so a moved directory would get a new
project with a new, empty data volume, while a copied one carries the original's state
along. The rule, data safety first (never two directories driving one project):

- recorded here: the recorded project is this fleet's;
- recorded at another path that still holds a fleet whose state names the same project
  (or cannot be read), or whose compose file made the project's containers: this directory
  is a **copy**, and the recorded deployment is that directory's;
- recorded at another path that no longer holds it: the directory was **moved**, and the
  recorded project is this fleet's;
- recorded without the path (a fleetctl before 2026-12-06): this fleet's when it is the
  directory's default project; otherwise moved and copied cannot be told apart
  (**unknown**).

Nothing here runs Docker: which compose files made a project's containers is asked through
a callable (``docker ps -a`` reading the containers' config-files label).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from fleetctl.deploy.compose import (
    COMPOSE_DIR,
    COMPOSE_FILE,
    Options,
    project_name,
    saved_state,
)
from fleetctl.errors import ConfigError, ConflictError

# Which compose files (absolute paths) made the containers of a project, running or not.
ComposeFilesOf = Callable[[str], set[str]]


class Origin(Enum):
    """How a fleet directory's recorded deployment came to be in it."""

    OWN = "own"  # recorded in this directory
    MOVED = "moved"  # recorded at a path that no longer holds it
    COPIED = "copied"  # recorded by another directory that still holds it
    UNKNOWN = "unknown"  # recorded without the path, under another project than the default


@dataclass(frozen=True)
class Recorded:
    """A fleet directory's recorded deployment and where it came from.

    Attributes:
        options: What ``up`` recorded.
        origin: Whose it is (:class:`Origin`).
        elsewhere: With ``MOVED``, the directory it was recorded in; with ``COPIED``, the
            directory whose deployment it is; otherwise ``None``.
    """

    options: Options
    origin: Origin
    elsewhere: Path | None = None

    @property
    def ours(self) -> bool:
        """Whether the recorded project may be acted on from this directory."""
        return self.origin is not Origin.COPIED


@dataclass(frozen=True)
class ProjectChoice:
    """The project ``up`` deploys as, and the line that says why (``""``: nothing to say)."""

    project: str
    note: str = ""


def recorded_deployment(fleet_dir: Path, compose_files_of: ComposeFilesOf) -> Recorded | None:
    """The deployment recorded in *fleet_dir* and whose it is; ``None`` when none is.

    Raises:
        ConfigError: *fleet_dir*'s state file is unreadable or malformed.
    """
    state = saved_state(fleet_dir)
    if state is None:
        return None
    here, options = fleet_dir.resolve(), state.options
    if state.fleet_dir is None:
        own = options.project == project_name(here)
        return Recorded(options, Origin.OWN if own else Origin.UNKNOWN)
    if state.fleet_dir == here:
        return Recorded(options, Origin.OWN)
    holder = _holder(state.fleet_dir, here, options.project, compose_files_of)
    if holder is not None:
        return Recorded(options, Origin.COPIED, holder)
    return Recorded(options, Origin.MOVED, state.fleet_dir)


def _holder(recorded_dir: Path, here: Path, project: str,
            compose_files_of: ComposeFilesOf) -> Path | None:
    """The other directory that still holds the deployment of *project*, if any."""
    if _holds_elsewhere(recorded_dir, here, project):
        return recorded_dir
    # `mv yard a; cp -a a b`: both recorded `yard`; the containers name the one that runs.
    for made_from in sorted(compose_files_of(project)):
        path = Path(made_from)
        if (path.name == COMPOSE_FILE and path.parent.name == COMPOSE_DIR
                and _holds_elsewhere(path.parent.parent, here, project)):
            return path.parent.parent
    return None


def _holds_elsewhere(directory: Path, here: Path, project: str) -> bool:
    """Whether *directory* is another fleet than *here* (not a link to it, as `mv yard
    prod; ln -s prod yard` leaves) whose recorded deployment is *project*."""
    try:
        if directory.resolve() == here:
            return False
    except (OSError, RuntimeError):  # a link loop: no fleet there
        return False
    return _holds(directory, project)


def _holds(directory: Path, project: str) -> bool:
    """Whether *directory* is a fleet whose recorded deployment is *project*.

    A state that cannot be read counts as holding it: it may be the original's, and
    taking its project over could stop its containers or delete its data.
    """
    if not os.path.lexists(directory / "fleet.yaml"):
        return False
    try:
        state = saved_state(directory)
    except (ConfigError, OSError):
        return True
    return state is not None and state.options.project == project


def project_for_up(fleet_dir: Path, compose_files_of: ComposeFilesOf) -> ProjectChoice:
    """The compose project ``up`` deploys *fleet_dir* as when ``--project`` is not given.

    Raises:
        ConfigError: *fleet_dir*'s state file is unreadable or malformed.
        ConflictError: *fleet_dir* is a copy whose default project is the one the
            original keeps (the copy sits where the original was first deployed).
    """
    default = project_name(fleet_dir)
    recorded = recorded_deployment(fleet_dir, compose_files_of)
    if recorded is None:
        return ProjectChoice(default)
    project = recorded.options.project
    if recorded.origin is Origin.OWN:
        return ProjectChoice(project)
    if recorded.origin is Origin.MOVED:
        return ProjectChoice(project, f"fleet directory moved from {recorded.elsewhere}: "
                                      f"keeping compose project {project} and its data volume")
    if recorded.origin is Origin.COPIED:
        return _for_copy(fleet_dir.resolve(), recorded, default)
    return ProjectChoice(default, (
        f"the deployment state here names compose project {project}, not {default} "
        "(written by a fleetctl that did not record the fleet directory): "
        f"{default} starts with an empty data volume; if this directory was moved, "
        f"`fleetctl up --project {project}` keeps the old one"))


def _for_copy(here: Path, recorded: Recorded, default: str) -> ProjectChoice:
    original = recorded.options.project
    if default == original:
        raise ConflictError(
            f"{here} is a copy of {recorded.elsewhere}, whose deployment is compose project "
            f"{original}, the name this directory's path gives: give this copy its own "
            f"with `fleetctl up --project NAME` (NAME other than {original})")
    return ProjectChoice(default, (
        f"{here} is a copy of {recorded.elsewhere}: compose project {default} starts with "
        f"an empty data volume ({original} and its data stay that directory's; to carry "
        f"them over, `fleetctl down` there and remove it, then `fleetctl down` and "
        f"`fleetctl up --project {original}` here)"))
