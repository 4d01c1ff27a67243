"""``fleetctl demo`` as a real subprocess for browser tests, and ROS helpers beside it.

:func:`running_demo` starts the demo exactly as a person would (``fleetctl demo`` on free
ports), reads what it prints (URLs, tokens, each robot's ``ROS_DOMAIN_ID``) with a deadline,
and on exit stops it with SIGTERM. Every process the demo started is recorded while it runs,
so the test can check afterwards that none outlived the demo; survivors are killed by pid so a
failing test leaves nothing behind either.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
import sys
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

HEALTHY_LINE = "fleetctl demo: all components healthy"
STOP_TIMEOUT_S = 30.0  # the demo gives each of its children 5 s after SIGTERM
REAP_TIMEOUT_S = 10.0  # after the demo is gone: how long orphans get to vanish
OUTPUT_LIMIT_LINES = 200  # lines of the demo's output kept for error messages

_PATTERNS = {
    "ws_url": re.compile(r"^\s+server\s+(ws://\S+)"),
    "webviz_url": re.compile(r"^\s+webviz\s+(http://\S+)"),
    "viewer_token": re.compile(r"^\s+viewer token .*:\s+(\S+)$"),
    "operator_token": re.compile(r"^\s+operator token .*:\s+(\S+)$"),
}
_ROBOT = re.compile(r"^\s+(\S+)\s+client from (\S+), ROS_DOMAIN_ID=(\d+)")


@dataclass
class RunningDemo:
    """What the demo printed, and which processes it started.

    Attributes:
        ws_url: the server's WebSocket URL.
        webviz_url: the web page's URL.
        viewer_token: token that may only receive.
        operator_token: token that may also send goal and initial poses.
        robot_domains: each robot's ``ROS_DOMAIN_ID``, by robot name.
        output: the demo's output lines so far (bounded by ``OUTPUT_LIMIT_LINES``).
        descendants: (pid, start time in clock ticks) of every process seen under the demo.
        survivors: descendants still alive after the demo exited (filled on exit).
        returncode: the demo's exit code (filled on exit); None if it had to be killed.
    """

    ws_url: str = ""
    webviz_url: str = ""
    viewer_token: str = ""
    operator_token: str = ""
    robot_domains: dict[str, int] = field(default_factory=dict)
    output: list[str] = field(default_factory=list)
    descendants: set[tuple[int, int]] = field(default_factory=set)
    survivors: list[int] = field(default_factory=list)
    returncode: int | None = None

    def parse(self, line: str) -> None:
        """Take what one output line of the demo says."""
        if len(self.output) < OUTPUT_LIMIT_LINES:
            self.output.append(line)
        for name, pattern in _PATTERNS.items():
            if match := pattern.match(line):
                setattr(self, name, match.group(1))
        if match := _ROBOT.match(line):
            self.robot_domains[match.group(1)] = int(match.group(3))


def _proc_stat(pid: int) -> tuple[int, int] | None:
    """(parent pid, start time in clock ticks) of *pid*, or None when it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    # The command name (field 2) may hold spaces and parentheses: split after its last ')'.
    fields = stat[stat.rindex(")") + 2 :].split()
    return int(fields[1]), int(fields[19])


def descendants_of(root: int) -> set[tuple[int, int]]:
    """Every live process under *root*, as (pid, start time) pairs (from /proc)."""
    children: dict[int, list[tuple[int, int]]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit() and (info := _proc_stat(int(entry))) is not None:
            children.setdefault(info[0], []).append((int(entry), info[1]))
    found: set[tuple[int, int]] = set()
    todo = [root]
    while todo:
        for child in children.get(todo.pop(), []):
            found.add(child)
            todo.append(child[0])
    return found


def _alive(pid: int, start_ticks: int) -> bool:
    info = _proc_stat(pid)
    return info is not None and info[1] == start_ticks  # same start time: not a reused pid


async def _read_until_healthy(
    proc: asyncio.subprocess.Process, demo: RunningDemo, timeout_s: float
) -> None:
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            output = "\n".join(demo.output)
            raise AssertionError(f"demo not healthy after {timeout_s} s:\n{output}")
        try:
            raw = await asyncio.wait_for(proc.stdout.readline(), left)
        except TimeoutError:
            continue  # the loop's deadline check reports it
        if not raw:
            await proc.wait()
            raise AssertionError(
                f"demo exited ({proc.returncode}) before it was healthy:\n" + "\n".join(demo.output)
            )
        line = raw.decode("utf-8", errors="replace").rstrip("\n")
        demo.parse(line)
        demo.descendants |= descendants_of(proc.pid)
        if line.startswith(HEALTHY_LINE):
            return


async def _stop(proc: asyncio.subprocess.Process, demo: RunningDemo) -> None:
    demo.descendants |= descendants_of(proc.pid)
    assert proc.stdout is not None
    if proc.returncode is None:
        proc.send_signal(signal.SIGTERM)
    try:
        # Drain the output while it stops, so a full pipe cannot block its shutdown.
        out = await asyncio.wait_for(proc.stdout.read(), STOP_TIMEOUT_S)
        await asyncio.wait_for(proc.wait(), STOP_TIMEOUT_S)
        demo.returncode = proc.returncode
        for line in out.decode("utf-8", errors="replace").splitlines():
            demo.parse(line)
    except TimeoutError:
        proc.kill()  # its children get SIGTERM from the kernel (PR_SET_PDEATHSIG)
        await proc.wait()
    deadline = time.monotonic() + REAP_TIMEOUT_S
    alive = [p for p in demo.descendants if _alive(*p)]
    while alive and time.monotonic() < deadline:
        await asyncio.sleep(0.05)  # polling interval of a deadline-bounded wait
        alive = [p for p in alive if _alive(*p)]
    demo.survivors = [pid for pid, _ in alive]
    for pid, ticks in alive:  # only processes this demo started, by pid
        if _alive(pid, ticks):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


@contextlib.asynccontextmanager
async def running_demo(
    workdir: Path, base_domain_id: int, startup_timeout_s: float = 45.0,
    extra_args: tuple[str, ...] = (),
) -> AsyncIterator[RunningDemo]:
    """Run ``fleetctl demo`` (2 robots, free ports) until the block ends.

    Args:
        workdir: the demo's fleet directory (its logs land in ``workdir/logs``).
        base_domain_id: ``ROS_DOMAIN_ID`` of robot1; robot2 uses the next one.
        startup_timeout_s: how long (s) the demo gets to print that it is healthy.
        extra_args: more ``fleetctl demo`` options (benchmarks/page_soak.py passes
            ``--duration``, so a soak whose runner dies leaves no fleet behind for long).

    Raises:
        AssertionError: the demo exited or was not healthy in time (with its output).
    """
    argv = [
        sys.executable, "-m", "fleetctl.cli.main", "demo", "--robots", "2", "--port", "0",
        "--webviz-port", "0", "--base-domain-id", str(base_domain_id),
        "--workdir", str(workdir), "--startup-timeout", str(startup_timeout_s), *extra_args,
    ]
    proc = await asyncio.create_subprocess_exec(
        *argv,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},  # its lines must reach us as printed
        stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
    )
    demo = RunningDemo()
    try:
        await _read_until_healthy(proc, demo, startup_timeout_s + 15.0)
        yield demo
    finally:
        await _stop(proc, demo)


@contextlib.asynccontextmanager
async def ros_process(domain_id: int, *args: str) -> AsyncIterator[asyncio.subprocess.Process]:
    """``python ARGS`` in ROS domain *domain_id*, stdout piped; terminated on exit."""
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    proc = await asyncio.create_subprocess_exec(
        sys.executable, *args, env=env, stdout=asyncio.subprocess.PIPE
    )
    try:
        yield proc
    finally:
        if proc.returncode is None:
            proc.terminate()
            try:
                await asyncio.wait_for(proc.wait(), 10)
            except TimeoutError:
                proc.kill()
                await proc.wait()
