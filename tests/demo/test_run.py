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


def test_domain_ids_past_232_are_one_error_naming_both_options(tmp_path: Path) -> None:
    """--base-domain-id 232 --robots 3 was a ValueError traceback (and an empty temporary
    directory left behind)."""
    workdir = tmp_path / "demo"
    with pytest.raises(FleetError) as info:
        run_demo(DemoOptions(robots=3, base_domain_id=232, workdir=workdir), print)
    assert str(info.value) == ("--base-domain-id 232 with --robots 3: robot3 would get "
                               "ROS_DOMAIN_ID 234; ROS 2 allows 0-232")
    assert info.value.exit_code == ExitCode.CONFIG
    assert not workdir.exists()
