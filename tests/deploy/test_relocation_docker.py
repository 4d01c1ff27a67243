"""A moved fleet directory keeps its deployment and its data; a copy gets its own (real
images, real compose, the `fleetctl` command line).

`init` -> `up` -> a marker file in the server's data volume -> `down` -> `mv` the directory
-> `up`: the same compose project, the same volume, the marker is there -> `down` ->
`cp -a` the directory -> `up` in the copy: another project, an empty volume, and a line
saying why.

Before 2026-12-06 the `up` after `mv` made a new project from the new path, with a new,
empty data volume: the robot registry and recordings looked lost (they were in the old
project's volume, which only `up --project OLD` found).
"""

from __future__ import annotations

import json
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.deploy.test_lifecycle_docker import FLEETCTL, Operator
from tests.deploy.test_live_docker import _new_fleet

pytestmark = [pytest.mark.docker, pytest.mark.slow]

MARKER = "/var/lib/fleetctl/relocation-marker"


def _project(fleet: Path) -> str:
    return str(json.loads((fleet / ".compose" / "state.json").read_text())["project"])


def _server(project: str) -> str:
    res = subprocess.run(
        ["docker", "ps", "-q", "--filter", f"label=com.docker.compose.project={project}",
         "--filter", "label=com.docker.compose.service=server"],
        capture_output=True, text=True, check=True)
    ids = res.stdout.split()
    assert len(ids) == 1, f"{project}: server containers {ids}"
    return ids[0]


def _data_volume(server: str) -> str:
    res = subprocess.run(["docker", "inspect", "--format", "{{json .Mounts}}", server],
                         capture_output=True, text=True, check=True)
    mounts = json.loads(res.stdout)
    return next(str(m["Name"]) for m in mounts if m["Destination"] == "/var/lib/fleetctl")


def _marker(server: str) -> str:
    res = subprocess.run(["docker", "exec", server, "cat", MARKER], capture_output=True,
                         text=True, check=False)
    return res.stdout.strip() if res.returncode == 0 else ""


class FleetDirs:
    """The fleet directories the test deploys, each taken down with its data at the end."""

    def __init__(self, op: Operator) -> None:
        self.op = op
        self.dirs: list[Path] = []
        self.projects: set[str] = set()

    def up(self, fleet: Path) -> str:
        """`fleetctl up --fleet FLEET` as a user types it; its stderr."""
        self.dirs.append(fleet)
        res = subprocess.run([FLEETCTL, "up", "--fleet", str(fleet), "--bind", "127.0.0.1"],
                             cwd=self.op.work, env=self.op.env, text=True,
                             capture_output=True, timeout=300, check=False)
        if (fleet / ".compose" / "state.json").is_file():
            self.projects.add(_project(fleet))
        assert res.returncode == 0, res.stdout + res.stderr
        return res.stderr

    def clean_up(self) -> None:
        """Every deployment down with its data; a volume no directory records any more
        (a regression: `up` after `mv` left the old project's behind) removed too."""
        for used in self.dirs:
            if (used / ".compose" / "state.json").is_file():
                self.op.run("down", "--fleet", str(used), "--delete-data", ok=False)
        for project in self.projects:
            subprocess.run(["docker", "volume", "rm", "-f", f"{project}_server-data"],
                           capture_output=True, check=False)

    def down(self, fleet: Path, *more: str) -> None:
        self.op.run("down", "--fleet", str(fleet), *more)


@pytest.fixture
def fleets(tmp_path: Path) -> Iterator[tuple[FleetDirs, Path]]:
    op, fleet, _unused = _new_fleet(tmp_path)
    dirs = FleetDirs(op)
    try:
        yield dirs, fleet
    finally:
        dirs.clean_up()


def test_a_moved_fleet_keeps_its_data_and_a_copy_gets_its_own(
        fleets: tuple[FleetDirs, Path], tmp_path: Path) -> None:
    dirs, fleet = fleets
    dirs.up(fleet)
    project = _project(fleet)
    server = _server(project)
    volume = _data_volume(server)
    assert volume == f"{project}_server-data"
    subprocess.run(["docker", "exec", server, "sh", "-c", f"echo kept > {MARKER}"],
                   check=True, capture_output=True)
    dirs.down(fleet)

    moved = tmp_path / "fleets" / "prod"
    moved.parent.mkdir()
    shutil.move(fleet, moved)
    said = dirs.up(moved)
    assert (f"fleetctl: fleet directory moved from {fleet.resolve()}: keeping compose "
            f"project {project} and its data volume") in said.splitlines()
    assert _project(moved) == project
    server = _server(project)
    assert (_data_volume(server), _marker(server)) == (volume, "kept")
    dirs.down(moved)

    copy = tmp_path / "prod-copy"
    subprocess.run(["cp", "-a", str(moved), str(copy)], check=True)
    said = dirs.up(copy)
    copied = _project(copy)
    assert copied != project
    assert any(line.startswith(f"fleetctl: {copy.resolve()} is a copy of {moved.resolve()}: "
                               f"compose project {copied} starts with an empty data volume")
               for line in said.splitlines()), said
    server = _server(copied)
    assert (_data_volume(server), _marker(server)) == (f"{copied}_server-data", "")


def test_a_fleet_moved_while_it_runs_comes_up_again_from_its_new_place(
        fleets: tuple[FleetDirs, Path], tmp_path: Path) -> None:
    """`mv` while the deployment runs: the old containers (made from a compose file that
    is gone) hold the fleet's ports; they are this fleet's, so `up` recreates them from
    the new place instead of refusing their ports as another program's."""
    dirs, fleet = fleets
    dirs.up(fleet)
    project = _project(fleet)
    subprocess.run(["docker", "exec", _server(project), "sh", "-c", f"echo kept > {MARKER}"],
                   check=True, capture_output=True)
    moved = tmp_path / "renamed"
    shutil.move(fleet, moved)
    dirs.up(moved)
    assert _project(moved) == project
    server = _server(project)
    assert _marker(server) == "kept"
    res = subprocess.run(["docker", "inspect", "--format",
                          '{{index .Config.Labels "com.docker.compose.project.config_files"}}',
                          server], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == str(moved.resolve() / ".compose" / "docker-compose.yml")
