"""An interrupted ``fleetctl e2e`` removes every container and network it made.

Runs the real command as a subprocess (the link scenario: base and router images only),
waits until its labelled containers exist, signals it, and checks that within a deadline
the process is gone with a clear message and nothing labelled with its run remains.
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from fleetctl.deploy.dockercli import image_exists
from fleetctl.deploy.images import BASE_IMAGE, image_tag
from fleetctl.e2e import cleanup

pytestmark = [
    pytest.mark.docker,
    pytest.mark.skipif(shutil.which("docker") is None, reason="needs docker"),
]

STARTUP_DEADLINE_S = 60.0
CLEANUP_DEADLINE_S = 30.0


def _wait(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out after {timeout_s} s: {what}"
        time.sleep(0.1)  # polling interval of a deadline-bounded wait


def _resources(run_id: str) -> list[cleanup.Resource]:
    return cleanup.find(cleanup.CLEANUP_RUNNER, f"{cleanup.RUN_LABEL}={run_id}")


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP],
                         ids=lambda s: signal.Signals(s).name)
def test_a_signal_removes_every_container_and_network_of_the_run(
        tmp_path: Path, signum: int) -> None:
    for image in (BASE_IMAGE, image_tag("router")):
        if not image_exists(cleanup.CLEANUP_RUNNER, image):
            pytest.fail(f"{image} missing: run `fleetctl build` first")
    run_id = "t" + secrets.token_hex(3)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "fleetctl.cli.main", "e2e", "--scenario", "link",
         "--duration", "120", "--out", str(tmp_path), "--run-id", run_id],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
        # Its own process group: if it must be killed, its docker children go with it and
        # release the pipes (else communicate() would wait for them).
        start_new_session=True)
    try:
        # The router and both probe containers: the run is in the middle of its work.
        _wait(lambda: sum(r.kind == "container" for r in _resources(run_id)) >= 3
              or proc.poll() is not None, STARTUP_DEADLINE_S, "the run's containers")
        assert proc.poll() is None, proc.communicate()
        assert any(r.kind == "network" for r in _resources(run_id))
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=CLEANUP_DEADLINE_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate(timeout=CLEANUP_DEADLINE_S)
        left = _resources(run_id)
        cleanup.remove(cleanup.CLEANUP_RUNNER, left)  # never leave them behind for the next test
    stderr = err.decode()
    assert left == [], (left, stderr)
    assert proc.returncode == 128 + signum, stderr
    name = signal.Signals(signum).name
    assert f"fleetctl: error: e2e run {run_id} interrupted by {name}" in stderr, stderr
    assert "every container and network of the run was removed" in stderr, stderr
    assert "Traceback" not in stderr, stderr
    assert not (tmp_path / "report.json").exists()
