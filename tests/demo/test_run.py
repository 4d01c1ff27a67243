"""fleetctl.demo.run: what fails before any component starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.demo.run import DemoOptions, run_demo
from fleetctl.errors import ExitCode, FleetError


def test_a_workdir_that_is_a_file_is_one_error(tmp_path: Path) -> None:
    workdir = tmp_path / "afile"
    workdir.write_text("x\n")
    with pytest.raises(FleetError, match=r"--workdir .*afile: cannot write the demo's files: "
                                         "Not a directory") as info:
        run_demo(DemoOptions(workdir=workdir), print)
    assert info.value.exit_code == ExitCode.CONFIG
    assert workdir.read_text() == "x\n"
