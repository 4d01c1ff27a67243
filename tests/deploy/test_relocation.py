"""Which compose project a moved or copied fleet directory deploys as (no Docker needed:
the docker CLI is a recorder that says which compose files made a project's containers).

`up` derived the project from the directory's path: after `mv ~/fleet ~/fleets/prod` it
started a new project with a new, empty data volume (robot registry, recordings), and the
fleet looked as if its data were gone. A copy (`cp -a`) kept the original's recorded
project, so `down --delete-data` in the copy deleted the original's data.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import pytest

from fleetctl.cli.main import main
from fleetctl.deploy import compose, composerun, hostports
from fleetctl.errors import ConflictError, FleetError
from tests.deploy.test_compose import FakeDocker, OtherFleets, _opts


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    fleet_dir = tmp_path / "yard"
    assert main(["init", str(fleet_dir), "--endpoint", "fleet.example:51820"]) == 0
    return fleet_dir


@pytest.fixture(autouse=True)
def host_ports_free(monkeypatch: pytest.MonkeyPatch) -> None:
    """`up` with a fake docker must not depend on what this machine's ports hold."""
    monkeypatch.setattr(hostports, "bind_error", lambda *_: None)


def _quiet(_line: str) -> None:
    pass


def _up(fleet_dir: Path, runner: FakeDocker | None = None, **kw: object) -> str:
    """`up` as the CLI runs it: the project chosen for this directory, then compose."""
    runner = runner or FakeDocker()
    choice = composerun.project_for_up(fleet_dir, kw.pop("project", None), runner=runner)
    composerun.up(fleet_dir, _opts(fleet_dir, wireguard="off", project=choice.project, **kw),
                  progress=_quiet, runner=runner)
    return choice.project


def _compose_file(fleet_dir: Path) -> str:
    return str(fleet_dir.resolve() / ".compose" / "docker-compose.yml")


def test_up_records_the_fleet_directory_it_ran_in(fleet: Path) -> None:
    _up(fleet)
    state = json.loads((fleet / ".compose" / "state.json").read_text())
    assert state["fleet_dir"] == str(fleet.resolve())


def test_a_moved_fleet_keeps_its_project_and_says_so(fleet: Path, tmp_path: Path) -> None:
    project = _up(fleet)
    moved = tmp_path / "fleets" / "prod"
    moved.parent.mkdir()
    fleet.rename(moved)
    choice = composerun.project_for_up(moved, None, runner=FakeDocker())
    assert choice.project == project
    assert choice.note == (f"fleet directory moved from {fleet.resolve()}: keeping compose "
                           f"project {project} and its data volume")
    assert composerun.existing_options(moved, runner=FakeDocker()).project == project
    # `up` there records the new home: from now on it is simply this fleet's project.
    assert _up(moved) == project
    again = composerun.project_for_up(moved, None, runner=FakeDocker())
    assert (again.project, again.note) == (project, "")


def test_a_moved_fleet_with_a_link_left_at_its_old_path_is_moved(
        fleet: Path, tmp_path: Path) -> None:
    """`mv yard prod; ln -s prod yard`: the old path holds this very fleet, not a copy."""
    project = _up(fleet)
    moved = tmp_path / "prod"
    fleet.rename(moved)
    fleet.symlink_to(moved)
    choice = composerun.project_for_up(moved, None, runner=FakeDocker())
    assert choice.project == project and choice.note.startswith("fleet directory moved")


def test_a_copy_gets_its_own_project_and_never_the_originals(
        fleet: Path, tmp_path: Path) -> None:
    project = _up(fleet)
    copy = tmp_path / "yard2"
    shutil.copytree(fleet, copy, symlinks=True)
    choice = composerun.project_for_up(copy, None, runner=FakeDocker())
    assert choice.project == compose.project_name(copy) != project
    assert choice.note.startswith(f"{copy.resolve()} is a copy of {fleet.resolve()}: "
                                  f"compose project {choice.project} starts with an empty "
                                  "data volume")
    # Before its own `up` the copy has no deployment: status/logs/down said the
    # original's, and `down --delete-data` deleted the original's data.
    with pytest.raises(FleetError, match=f"no deployment here: .* a copy of {fleet.resolve()}"):
        composerun.existing_options(copy, runner=FakeDocker())
    running = OtherFleets({project: [_compose_file(fleet)]})
    recorded = composerun.existing_options(fleet, runner=running)
    for delete_data in (False, True):
        with pytest.raises(ConflictError, match=f"made from {_compose_file(fleet)}"):
            composerun.down(copy, recorded, delete_data=delete_data, progress=_quiet,
                            runner=running)
    stopped = OtherFleets({})
    with pytest.raises(ConflictError, match="its volumes are not deleted"):
        composerun.down(copy, recorded, delete_data=True, progress=_quiet, runner=stopped)
    assert not stopped.compose_calls() and not running.compose_calls()
    # Its own `up`: its own project, from then on.
    assert _up(copy) == choice.project
    assert composerun.existing_options(copy, runner=FakeDocker()).project == choice.project


def test_a_copy_of_a_moved_fleet_running_elsewhere_is_a_copy(
        fleet: Path, tmp_path: Path) -> None:
    """`mv yard a; cp -a a b`: both recorded the same old path, which holds nothing now;
    a's containers (from its compose file) tell that b is the copy."""
    project = _up(fleet)
    moved, copy = tmp_path / "a", tmp_path / "b"
    fleet.rename(moved)
    shutil.copytree(moved, copy, symlinks=True)
    running = OtherFleets({project: [_compose_file(moved)]})
    assert _up(moved, running) == project
    choice = composerun.project_for_up(copy, None, runner=running)
    assert choice.project == compose.project_name(copy)
    assert f"is a copy of {moved.resolve()}" in choice.note


def test_up_never_drives_a_project_another_directory_runs(
        fleet: Path, tmp_path: Path) -> None:
    """Even when asked (`--project P`): compose would recreate the other fleet's
    containers from this file and remove its simulated robots as orphans."""
    other = tmp_path / "other"
    shutil.copytree(fleet, other, symlinks=True)
    project = _up(other)
    running = OtherFleets({project: [_compose_file(other)]})
    with pytest.raises(ConflictError, match=f"compose project {project} has containers made "
                                            f"from {_compose_file(other)}"):
        _up(fleet, running, project=project)
    assert not running.compose_calls()


def test_a_copy_at_the_path_that_named_the_originals_project_is_refused(
        fleet: Path, tmp_path: Path) -> None:
    """`mv yard a; up in a; cp -a a yard`: the copy's default project is the one a keeps."""
    project = _up(fleet)
    moved = tmp_path / "a"
    fleet.rename(moved)
    _up(moved)
    shutil.copytree(moved, fleet, symlinks=True)
    with pytest.raises(ConflictError, match=f"--project NAME.*{project}"):
        composerun.project_for_up(fleet, None, runner=FakeDocker())
    # Nor is the original's data this path's to delete (a moved fleet's default name is).
    docker = OtherFleets({})
    given = composerun.existing_options(fleet, project, runner=docker)
    with pytest.raises(ConflictError, match="its volumes are not deleted"):
        composerun.down(fleet, given, delete_data=True, progress=_quiet, runner=docker)
    assert not docker.compose_calls()
    assert composerun.project_for_up(fleet, "yard2", runner=FakeDocker()).project == "yard2"


def _forget_the_directory(fleet_dir: Path) -> None:
    """The state as a fleetctl before 2026-12-06 wrote it: no fleet_dir."""
    state = fleet_dir / ".compose" / "state.json"
    data = json.loads(state.read_text())
    del data["fleet_dir"]
    state.write_text(json.dumps(data))


def test_a_state_without_the_directory_keeps_working(fleet: Path, tmp_path: Path) -> None:
    project = _up(fleet)
    _forget_the_directory(fleet)
    here = composerun.project_for_up(fleet, None, runner=FakeDocker())
    assert (here.project, here.note) == (project, "")
    assert composerun.existing_options(fleet, runner=FakeDocker()).project == project
    moved = tmp_path / "prod"
    fleet.rename(moved)
    # Moved or copied cannot be told: a new project as before, and how to keep the data.
    choice = composerun.project_for_up(moved, None, runner=FakeDocker())
    assert choice.project == compose.project_name(moved)
    assert choice.note == (
        f"the deployment state here names compose project {project}, not "
        f"{choice.project} (written by a fleetctl that did not record the fleet directory): "
        f"{choice.project} starts with an empty data volume; if this directory was moved, "
        f"`fleetctl up --project {project}` keeps the old one")
    assert composerun.existing_options(moved, runner=FakeDocker()).project == project


def test_a_given_project_is_used_as_given(fleet: Path, tmp_path: Path) -> None:
    _up(fleet)
    moved = tmp_path / "prod"
    fleet.rename(moved)
    choice = composerun.project_for_up(moved, "chosen", runner=FakeDocker())
    assert (choice.project, choice.note) == ("chosen", "")
    recorded = composerun.existing_options(moved, "chosen", runner=FakeDocker())
    assert recorded.project == "chosen"


def test_a_damaged_state_file_at_the_old_path_counts_as_the_original(
        fleet: Path, tmp_path: Path) -> None:
    """Data safety first: what cannot be read might be the original's deployment."""
    _up(fleet)
    copy = tmp_path / "yard2"
    shutil.copytree(fleet, copy, symlinks=True)
    (fleet / ".compose" / "state.json").write_text("{damaged")
    choice = composerun.project_for_up(copy, None, runner=FakeDocker())
    assert choice.project == compose.project_name(copy)


def test_the_old_path_holding_another_fleet_means_moved(fleet: Path, tmp_path: Path) -> None:
    """`mv yard prod; fleetctl init yard`: the new fleet at the old path is not this one."""
    project = _up(fleet)
    moved = tmp_path / "prod"
    fleet.rename(moved)
    shutil.copytree(moved, fleet, symlinks=True)
    state = fleet / ".compose" / "state.json"
    state.write_text(json.dumps({**json.loads(state.read_text()), "project": "newfleet"}))
    assert composerun.project_for_up(moved, None, runner=FakeDocker()).project == project


def test_down_delete_data_of_a_moved_fleet_is_its_own(fleet: Path, tmp_path: Path) -> None:
    project = _up(fleet)
    moved = tmp_path / "prod"
    fleet.rename(moved)
    docker = OtherFleets({})
    recorded = composerun.existing_options(moved, runner=docker)
    composerun.down(moved, recorded, delete_data=True, progress=_quiet, runner=docker)
    down = docker.compose_calls()[-1]
    assert down[down.index("-p") + 1] == project and "-v" in down
    # ... and another project is still refused with --delete-data.
    with pytest.raises(ConflictError):
        composerun.down(moved, replace(recorded, project="gone"), delete_data=True,
                        progress=_quiet, runner=docker)


def test_a_plain_up_keeps_a_project_given_before(fleet: Path) -> None:
    """`up --project P` then `up`: the second made the default project, with another empty
    data volume (or was refused on a running fleet)."""
    assert _up(fleet, project="chosen") == "chosen"
    choice = composerun.project_for_up(fleet, None, runner=FakeDocker())
    assert (choice.project, choice.note) == ("chosen", "")
