"""Unit tests of the demo's process supervisor (real child processes, no ROS)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fleetctl.demo.supervisor import ProcessSpec, Supervisor
from fleetctl.errors import FleetError
from fleetctl.waiting import wait_until


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_stop_all_ends_children_and_grandchildren(tmp_path: Path) -> None:
    pid_file = tmp_path / "grandchild.pid"
    # The child starts a grandchild, writes its pid, and waits forever.
    script = (
        "import subprocess, sys, time, pathlib\n"
        "p = subprocess.Popen([sys.executable, '-c', 'import time\\nwhile True: time.sleep(1)'])\n"
        f"pathlib.Path({str(pid_file)!r}).write_text(str(p.pid))\n"
        "while True: time.sleep(1)\n"
    )
    supervisor = Supervisor()
    child = supervisor.start(ProcessSpec("c", [sys.executable, "-c", script], tmp_path / "c.log"))
    wait_until(lambda: pid_file.exists() and pid_file.read_text(), 10.0, describe="grandchild")
    grandchild = int(pid_file.read_text())
    codes = supervisor.stop_all(grace_s=5.0)
    assert codes["c"] != 0
    assert not _alive(child)
    wait_until(lambda: not _alive(grandchild), 5.0, describe="grandchild exit")


def test_stop_all_kills_a_child_that_ignores_sigterm(tmp_path: Path) -> None:
    ready = tmp_path / "ready"
    script = (
        "import signal, time, pathlib\n"
        "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
        f"pathlib.Path({str(ready)!r}).write_text('1')\n"
        "while True: time.sleep(1)\n"
    )
    supervisor = Supervisor()
    supervisor.start(ProcessSpec("stubborn", [sys.executable, "-c", script], tmp_path / "s.log"))
    wait_until(ready.exists, 10.0, describe="ready file")
    started = time.monotonic()
    codes = supervisor.stop_all(grace_s=0.5)
    assert codes["stubborn"] == -9
    assert time.monotonic() - started < 5.0


def test_exited_and_log_tail_report_a_crash(tmp_path: Path) -> None:
    supervisor = Supervisor()
    argv = [sys.executable, "-c", "import sys; print('boom'); sys.exit(3)"]
    supervisor.start(ProcessSpec("crash", argv, tmp_path / "crash.log"))
    wait_until(lambda: "crash" in supervisor.exited(), 10.0, describe="crash")
    assert supervisor.exited() == {"crash": 3}
    assert "boom" in supervisor.log_tail("crash")
    assert supervisor.stop_all() == {"crash": 3}


def test_start_reports_a_missing_program(tmp_path: Path) -> None:
    with pytest.raises(FleetError, match="cannot start nothing"):
        Supervisor().start(ProcessSpec("nothing", ["/nonexistent/prog"], tmp_path / "n.log"))


def test_children_die_with_a_killed_supervisor(tmp_path: Path) -> None:
    pid_file = tmp_path / "child.pid"
    # A supervising process that starts one child, reports its pid, then waits forever.
    script = (
        "import sys, time, pathlib\n"
        "from fleetctl.demo.supervisor import ProcessSpec, Supervisor\n"
        "s = Supervisor()\n"
        f"pid = s.start(ProcessSpec('c', [sys.executable, '-c', 'import time\\nwhile True: "
        f"time.sleep(1)'], pathlib.Path({str(tmp_path / 'c.log')!r})))\n"
        f"pathlib.Path({str(pid_file)!r}).write_text(str(pid))\n"
        "while True: time.sleep(1)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", script])
    try:
        wait_until(lambda: pid_file.exists() and pid_file.read_text(), 10.0, describe="child")
        child = int(pid_file.read_text())
        parent.kill()
        parent.wait()
        wait_until(lambda: not _alive(child), 10.0, describe="the orphan to exit")
    finally:
        if parent.poll() is None:
            parent.kill()
