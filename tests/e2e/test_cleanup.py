"""Labels and removal by label (a fake docker: no engine needed)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import pytest

from fleetctl.deploy.dockercli import Completed
from fleetctl.e2e import cleanup
from fleetctl.e2e.topology import Topology
from fleetctl.errors import FleetError


class FakeDocker:
    """Answers ``ps``/``network ls`` from a table; records every command."""

    def __init__(self, containers: list[str], networks: list[str]) -> None:
        self.rows = {"container": containers, "network": networks}
        self.calls: list[list[str]] = []

    def __call__(self, argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        argv = list(argv)
        self.calls.append(argv)
        out = ""
        if argv[1:3] == ["ps", "-a"] or argv[1:3] == ["network", "ls"]:
            kind = "container" if argv[1] == "ps" else "network"
            want = argv[argv.index("--filter") + 1].removeprefix("label=")
            out = "".join(row + "\n" for row in self.rows[kind]
                          if want == cleanup.LABEL or f"\t{want.split('=')[1]}\t" in row)
        elif argv[1] == "rm":
            self.rows["container"] = [r for r in self.rows["container"]
                                      if r.split("\t")[0] not in argv[3:]]
        elif argv[1:3] == ["network", "rm"]:
            self.rows["network"] = [r for r in self.rows["network"]
                                    if r.split("\t")[0] != argv[3]]
        return Completed(tuple(argv), 0, out, "")


def test_label_args_name_the_run_and_its_owner() -> None:
    assert cleanup.label_args("ab12", "h:1:2") == [
        "--label", "io.fleetctl.e2e", "--label", "fleetctl.e2e.run=ab12",
        "--label", "fleetctl.e2e.owner=h:1:2"]


def test_this_process_is_alive_and_a_reused_pid_is_not(tmp_path: Path) -> None:
    me = cleanup.owner()
    assert cleanup.owner_alive(me) is True
    host, pid, start = me.split(":")
    assert cleanup.owner_alive(f"{host}:{pid}:{int(start) + 1}") is False
    stat = tmp_path / "4242" / "stat"
    stat.parent.mkdir()
    stat.write_text("4242 (a name) with spaces) S " + " ".join(["0"] * 18) + " 777 0\n")
    assert cleanup.owner_alive(f"{host}:4242:777", tmp_path) is True
    assert cleanup.owner_alive(f"{host}:4243:777", tmp_path) is False
    assert cleanup.owner_alive("another-host:1:1") is None
    assert cleanup.owner_alive("garbage") is None


def test_leftovers_are_runs_whose_owner_is_gone() -> None:
    me, dead = cleanup.owner(), cleanup.owner(os.getpid()).rsplit(":", 1)[0] + ":0"
    docker = FakeDocker(
        [f"fce2e-a-router\ta\t{dead}", f"fce2e-b-router\tb\t{me}",
         "fce2e-c-router\t<no value>\t<no value>"],
        [f"fce2e-a-robot\ta\t{dead}", "fce2e-d-robot\td\tother-host:1:1"])
    gone, kept = cleanup.leftovers(docker)
    assert [r.name for r in gone] == ["fce2e-a-router", "fce2e-a-robot"]
    assert {r.name for r in kept} == {"fce2e-b-router", "fce2e-c-router", "fce2e-d-robot"}
    gone, kept = cleanup.leftovers(docker, everything=True)
    assert [r.name for r in kept] == ["fce2e-b-router"]
    assert cleanup.remove(docker, gone) == gone
    assert docker.rows == {"container": [f"fce2e-b-router\tb\t{me}"], "network": []}


def test_find_raises_when_docker_fails() -> None:
    def broken(argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        return Completed(tuple(argv), 1, "", "Cannot connect to the Docker daemon")

    with pytest.raises(FleetError, match="Cannot connect"):
        cleanup.find(broken)


def test_close_removes_what_only_the_label_knows() -> None:
    # A container whose `docker run` a signal cut short: never recorded, labelled all the same.
    docker = FakeDocker(["fce2e-r1-server\tr1\th:1:1"], ["fce2e-r1-robot\tr1\th:1:1"])
    topo = Topology(run_id="r1", runner=docker, owner="h:1:1")
    topo.close()
    assert docker.rows == {"container": [], "network": []}
    assert ["docker", "rm", "-f", "-v", "fce2e-r1-server"] in docker.calls
