"""Labels on everything an e2e run creates, and removal by label.

Every container and network of a run carries three labels:

- ``io.fleetctl.e2e`` (no value): made by ``fleetctl e2e`` (older runs had only this one);
- ``fleetctl.e2e.run=<run id>``: which run; :meth:`Topology.close` removes by it, so a
  container whose ``docker run`` had not returned when a signal came is removed too;
- ``fleetctl.e2e.owner=<host>:<pid>:<start>``: the ``fleetctl e2e`` process that owns it
  (``start`` is the process's start time in clock ticks since boot, from ``/proc``, so a
  reused pid is not mistaken for the owner).

``fleetctl e2e --cleanup`` removes what crashed runs left: resources whose owner process is
gone. Runs still in progress on this host are left alone; a resource owned by another host
(a shared Docker engine) or without an owner label (an older run) counts as a leftover only
with ``--all`` (:func:`leftovers` ``everything=True``).
"""

from __future__ import annotations

import os
import socket
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from fleetctl.deploy.dockercli import Runner, check, deadline_runner

LABEL = "io.fleetctl.e2e"
RUN_LABEL = "fleetctl.e2e.run"
OWNER_LABEL = "fleetctl.e2e.owner"

# Listing and removing are quick and safe to repeat: each try gets 30 s, three tries, so an
# interrupted run's cleanup ends within minutes whatever the engine does
# (dockercli.deadline_runner says what was seen).
CLEANUP_RUNNER = deadline_runner(30.0, tries=3)


def run_runner(duration_s: float) -> Runner:
    """The runner of an e2e run's docker commands: each gets a deadline, tried once.

    The longest command is a measurement inside a container, a fraction of *duration_s*;
    a command past the deadline fails the scenario with its name instead of hanging the run.
    """
    return deadline_runner(max(120.0, 2 * duration_s + 60.0))


def _start_ticks(pid: int, proc: Path = Path("/proc")) -> str | None:
    """Field 22 of ``/proc/PID/stat`` (start time since boot, clock ticks); None: no process."""
    try:
        stat = (proc / str(pid) / "stat").read_text()
    except OSError:
        return None
    # The command name (field 2) is in parentheses and may hold spaces: split after it.
    return stat[stat.rfind(")") + 2:].split()[19]


def owner(pid: int | None = None) -> str:
    """This process's owner label value, ``host:pid:start``."""
    pid = os.getpid() if pid is None else pid
    return f"{socket.gethostname()}:{pid}:{_start_ticks(pid) or '?'}"


def owner_alive(value: str, proc: Path = Path("/proc")) -> bool | None:
    """Whether the owner *value* names a running process: None when it cannot be told.

    It cannot be told for another host's process or a malformed value.
    """
    host, _, rest = value.partition(":")
    pid, _, start = rest.partition(":")
    if host != socket.gethostname() or not pid.isdigit():
        return None
    return _start_ticks(int(pid), proc) == start


def label_args(run_id: str, owner_value: str) -> list[str]:
    """``docker run``/``network create`` arguments that label a resource of run *run_id*."""
    return ["--label", LABEL, "--label", f"{RUN_LABEL}={run_id}",
            "--label", f"{OWNER_LABEL}={owner_value}"]


@dataclass(frozen=True)
class Resource:
    """A labelled container or network.

    Attributes:
        kind: ``container`` or ``network``.
        name: Its name.
        run_id: Its run (empty for an older run without the label).
        owner: Its owner label value (empty when absent).
    """

    kind: str
    name: str
    run_id: str
    owner: str


def find(runner: Runner, label_filter: str = LABEL) -> list[Resource]:
    """Every container (running or not) and network matching ``--filter label=<filter>``.

    Raises:
        FleetError: docker failed (the engine is not reachable).
    """
    labels = [f'{{{{.Label "{k}"}}}}' for k in (RUN_LABEL, OWNER_LABEL)]
    found: list[Resource] = []
    for kind, argv, name in (("container", ["docker", "ps", "-a"], "{{.Names}}"),
                             ("network", ["docker", "network", "ls"], "{{.Name}}")):
        fmt = "\t".join([name, *labels])
        res = check(runner([*argv, "--filter", f"label={label_filter}", "--format", fmt],
                           None, True), f"list e2e {kind}s")
        for line in res.stdout.splitlines():
            name, run_id, own = [*line.split("\t"), "", ""][:3]
            found.append(Resource(kind, name, run_id.replace("<no value>", ""),
                                  own.replace("<no value>", "")))
    return found


def remove(runner: Runner, resources: Sequence[Resource]) -> list[Resource]:
    """Remove *resources*, containers first (best effort); returns what is gone now."""
    containers = [r.name for r in resources if r.kind == "container"]
    if containers:
        runner(["docker", "rm", "-f", "-v", *containers], None, True)
    for net in (r for r in resources if r.kind == "network"):
        runner(["docker", "network", "rm", net.name], None, True)
    left = {(r.kind, r.name) for r in find(runner)}
    return [r for r in resources if (r.kind, r.name) not in left]


def remove_run(runner: Runner, run_id: str) -> list[Resource]:
    """Remove every container and network labelled with *run_id*; returns what was removed."""
    return remove(runner, find(runner, f"{RUN_LABEL}={run_id}"))


def leftovers(runner: Runner, *, everything: bool = False) -> tuple[list[Resource],
                                                                    list[Resource]]:
    """Resources of e2e runs split into (leftovers, kept).

    A resource is a leftover when its owner process is gone; with *everything*, also when
    that cannot be told (another host, no owner label). Resources of runs in progress here
    are always kept.
    """
    gone, kept = [], []
    for r in find(runner):
        alive = owner_alive(r.owner) if r.owner else None
        if alive is False or (alive is None and everything):
            gone.append(r)
        else:
            kept.append(r)
    return gone, kept
