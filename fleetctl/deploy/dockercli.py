"""Thin, replaceable access to the ``docker`` command line.

Everything that talks to the Docker engine goes through a :class:`Runner`, so unit tests can
record the commands instead of running them. The CLI is used (not an SDK) because the
machines this runs on have the docker CLI but not always a matching Python SDK.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from fleetctl.errors import EnvironmentMissing, FleetError


@dataclass(frozen=True)
class Completed:
    """Result of one command.

    Attributes:
        args: The command that ran.
        returncode: Its exit status.
        stdout: Captured standard output (empty when not captured).
        stderr: Captured standard error (empty when not captured).
    """

    args: tuple[str, ...]
    returncode: int
    stdout: str
    stderr: str


# A runner takes (argv, stdin bytes or None, capture) and returns the result; it never raises
# on a non-zero exit, callers decide.
Runner = Callable[[Sequence[str], bytes | None, bool], Completed]


def _run(argv: Sequence[str], stdin: bytes | None, capture: bool,
         timeout_s: float | None) -> Completed:
    """Run *argv* once; raises ``subprocess.TimeoutExpired`` (child killed) past *timeout_s*."""
    try:
        proc = subprocess.run(
            list(argv),
            input=stdin,
            stdout=subprocess.PIPE if capture else None,
            stderr=subprocess.PIPE if capture else None,
            check=False,
            timeout=timeout_s,
        )
    except FileNotFoundError as exc:
        raise EnvironmentMissing(f"{argv[0]}: command not found") from exc
    out = proc.stdout.decode(errors="replace") if capture and proc.stdout else ""
    err = proc.stderr.decode(errors="replace") if capture and proc.stderr else ""
    return Completed(tuple(argv), proc.returncode, out, err)


def subprocess_runner(argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
    """Run *argv* for real; output is inherited (shown to the user) unless *capture*."""
    return _run(argv, stdin, capture, None)


# The exit status a command killed at its deadline reports (as coreutils `timeout` does).
DEADLINE_EXIT = 124


def deadline_runner(deadline_s: float, *, tries: int = 1) -> Runner:
    """A runner that kills a command still running after *deadline_s* and tries it again.

    Why: on Docker 20.10 a ``docker ps`` or ``docker exec`` started while the engine was
    removing containers has been seen to spin for over 30 minutes without returning, and
    whoever waited for it (``fleetctl e2e``'s cleanup, a test's ``finally``) waited forever;
    a second try of the same command answered at once. Use ``tries > 1`` only for commands
    that are safe to repeat (queries, ``rm -f``). After the last try the result has exit
    status :data:`DEADLINE_EXIT` and a stderr naming the command and the deadline, so
    :func:`check` reports it.
    """
    def run(argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        for _ in range(tries):
            try:
                return _run(argv, stdin, capture, deadline_s)
            except subprocess.TimeoutExpired:
                continue  # subprocess.run has killed and reaped it
        what = " ".join(argv[:3])
        return Completed(tuple(argv), DEADLINE_EXIT, "",
                         f"`{what}` did not return within {deadline_s:g} s "
                         f"({tries} {'try' if tries == 1 else 'tries'}); killed")
    return run


def require_docker(which: Callable[[str], str | None] = shutil.which) -> str:
    """Return the docker CLI path or raise a clear error when Docker is absent.

    Raises:
        EnvironmentMissing: no ``docker`` on PATH.
    """
    path = which("docker")
    if path is None:
        raise EnvironmentMissing(
            "docker: command not found; install Docker (Debian: apt-get install docker.io)"
        )
    return path


def docker_unreachable(runner: Runner = subprocess_runner) -> str | None:
    """Why the Docker engine cannot be asked anything (no docker command, no daemon at
    ``DOCKER_HOST``), in one line, or ``None`` when it answers."""
    try:
        res = runner(["docker", "version", "--format", "{{.Server.Version}}"], None, True)
    except EnvironmentMissing as exc:
        return str(exc)
    if res.returncode == 0:
        return None
    lines = (res.stderr or res.stdout).strip().splitlines()
    return lines[-1].strip() if lines else f"docker version exited {res.returncode}"


def require_docker_engine(runner: Runner = subprocess_runner) -> None:
    """Refuse to go on when the Docker engine does not answer: compose (v1) then printed
    a Python traceback of its own before fleetctl's one line.

    Raises:
        EnvironmentMissing: naming why (exit 5).
    """
    require_docker()
    if (why := docker_unreachable(runner)) is not None:
        raise EnvironmentMissing(f"cannot reach the Docker engine: {why}")


def check(result: Completed, what: str) -> Completed:
    """Raise a :class:`FleetError` naming *what* failed when *result* is non-zero."""
    if result.returncode != 0:
        detail = (result.stderr or result.stdout or "").strip().splitlines()[-5:]
        # A command whose output went straight to the terminal left nothing to quote.
        said = " | ".join(detail) if detail else "its output is above"
        raise FleetError(f"{what} failed (exit {result.returncode}): {said}")
    return result


# The label compose puts on a container naming the file(s) it came from.
CONFIG_FILES_LABEL = "com.docker.compose.project.config_files"


def fleet_filters(project: str, compose_file: Path) -> list[str]:
    """``docker ps`` filters for the containers compose made for *project* from
    *compose_file*: a container of the same project name from another fleet directory is
    not this fleet's."""
    return ["--filter", f"label=com.docker.compose.project={project}",
            "--filter", f"label={CONFIG_FILES_LABEL}={compose_file}"]


def image_exists(runner: Runner, image: str) -> bool:
    """True when the local engine has *image* (no registry is consulted)."""
    res = runner(["docker", "image", "inspect", "--format", "{{.Id}}", image], None, True)
    return res.returncode == 0
