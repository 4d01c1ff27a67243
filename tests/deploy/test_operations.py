"""fleetctl.deploy.operations: inputs an operator can get wrong, reported as one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.deploy import operations as ops
from fleetctl.errors import ConfigError


@pytest.mark.parametrize("sub", ["afile", "afile/fleet"])
def test_init_on_a_file_is_a_config_error(tmp_path: Path, sub: str) -> None:
    (tmp_path / "afile").write_text("not a directory\n")
    with pytest.raises(ConfigError, match="afile exists and is not a directory"):
        ops.create_fleet(tmp_path / sub)
    assert (tmp_path / "afile").read_text() == "not a directory\n"


def test_init_in_a_new_nested_directory_still_works(tmp_path: Path) -> None:
    ops.create_fleet(tmp_path / "a" / "b", dry_run=True)
