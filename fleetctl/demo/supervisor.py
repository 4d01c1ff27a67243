"""Start, watch and stop the demo's child processes, leaving no orphans.

Every child runs in its own session (process group), so stopping it also stops anything it
started. Stopping sends SIGTERM to the group, waits up to a deadline for it to exit, then
sends SIGKILL: a hung child can delay shutdown by at most that deadline. On Linux each child
also gets SIGTERM from the kernel if the supervising process dies without stopping it
(``PR_SET_PDEATHSIG``), so even a SIGKILLed demo leaves no orphans behind.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from fleetctl.errors import FleetError


@dataclass(frozen=True)
class ProcessSpec:
    """One child process.

    Attributes:
        name: label used in messages and the log file name.
        argv: the command line.
        env: variables set on top of this process's environment.
        log_path: file receiving the child's stdout and stderr.
    """

    name: str
    argv: Sequence[str]
    log_path: Path
    env: Mapping[str, str] = field(default_factory=dict)


@dataclass
class _Child:
    spec: ProcessSpec
    process: subprocess.Popen[bytes]
    log: IO[bytes]


class Supervisor:
    """Owns a set of child processes; :meth:`stop_all` ends every one of them."""

    def __init__(self) -> None:
        self._children: list[_Child] = []

    def start(self, spec: ProcessSpec) -> int:
        """Start *spec*'s process in a new session; return its pid.

        Raises:
            FleetError: the program could not be started.
        """
        spec.log_path.parent.mkdir(parents=True, exist_ok=True)
        log = spec.log_path.open("ab")
        try:
            process = subprocess.Popen(
                list(spec.argv),
                env={**os.environ, **spec.env},
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                preexec_fn=_die_with_parent,
            )
        except OSError as exc:
            log.close()
            raise FleetError(f"cannot start {spec.name} ({spec.argv[0]}): {exc}") from exc
        self._children.append(_Child(spec, process, log))
        return process.pid

    def exited(self) -> dict[str, int]:
        """Children that have exited, by name, with their exit codes."""
        return {
            child.spec.name: code
            for child in self._children
            if (code := child.process.poll()) is not None
        }

    def log_tail(self, name: str, max_bytes: int = 2000) -> str:
        """The last *max_bytes* of child *name*'s log (for error messages)."""
        for child in self._children:
            if child.spec.name == name:
                data = child.spec.log_path.read_bytes()[-max_bytes:]
                return data.decode("utf-8", errors="replace")
        return ""

    def stop_all(self, grace_s: float = 5.0) -> dict[str, int]:
        """Stop every child (newest first) and return their exit codes by name.

        Args:
            grace_s: how long (s) each child gets after SIGTERM before SIGKILL.
        """
        codes: dict[str, int] = {}
        for child in reversed(self._children):
            codes[child.spec.name] = _stop(child.process, grace_s)
            child.log.close()
        self._children.clear()
        return codes


_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """In the child before exec: ask the kernel for SIGTERM when the parent dies (Linux)."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


def _signal_group(process: subprocess.Popen[bytes], signum: int) -> None:
    # The child leads its own session, so its pid is the group id; the group may be gone.
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(process.pid, signum)


def _stop(process: subprocess.Popen[bytes], grace_s: float) -> int:
    if process.poll() is None:
        _signal_group(process, signal.SIGTERM)
        try:
            process.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            _signal_group(process, signal.SIGKILL)
            process.wait()
    # Grandchildren that outlived the leader are still in the group: end them too.
    _signal_group(process, signal.SIGKILL)
    return int(process.returncode)


