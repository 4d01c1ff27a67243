"""The docker CLI runners: output captured, a hung command killed at its deadline."""

from __future__ import annotations

import sys
import time

import pytest

from fleetctl.deploy.dockercli import (
    DEADLINE_EXIT,
    Completed,
    check,
    deadline_runner,
    subprocess_runner,
)
from fleetctl.errors import EnvironmentMissing, FleetError


def test_subprocess_runner_captures_output_and_status() -> None:
    res = subprocess_runner([sys.executable, "-c", "import sys; print('out'); "
                             "print('err', file=sys.stderr); sys.exit(3)"], None, True)
    assert (res.returncode, res.stdout, res.stderr) == (3, "out\n", "err\n")


def test_a_missing_command_is_a_clear_error() -> None:
    with pytest.raises(EnvironmentMissing, match="no-such-docker-cli: command not found"):
        deadline_runner(5.0)(["no-such-docker-cli", "ps"], None, True)


def test_a_command_within_its_deadline_returns_its_result() -> None:
    res = deadline_runner(30.0, tries=3)([sys.executable, "-c", "print(input())"], b"hi\n",
                                         True)
    assert (res.returncode, res.stdout) == (0, "hi\n")


def test_a_hung_command_is_killed_tried_again_and_named(tmp_path) -> None:
    tries = tmp_path / "tries"
    hang = f"open({str(tries)!r}, 'a').write('x'); import time; time.sleep(60)"
    start = time.monotonic()
    res = deadline_runner(0.5, tries=3)([sys.executable, "-c", hang], None, True)
    assert time.monotonic() - start < 20  # three 0.5 s deadlines, not three minutes
    assert tries.read_text() == "xxx"
    assert res.returncode == DEADLINE_EXIT
    with pytest.raises(FleetError, match=r"list things failed \(exit 124\): `.*python.* -c "
                                         r"open.*` did not return within 0.5 s \(3 tries\)"):
        check(res, "list things")


def test_a_failure_whose_output_went_to_the_terminal_points_there() -> None:
    # `compose up` streams its output (capture off): there is nothing to quote.
    with pytest.raises(FleetError, match=r"^compose up failed \(exit 1\): its output is above$"):
        check(Completed(("docker", "compose", "up"), 1, "", ""), "compose up")
    with pytest.raises(FleetError, match=r"failed \(exit 2\): line 2 \| bind: in use$"):
        check(Completed(("docker",), 2, "", "line 2\nbind: in use\n"), "docker run")
