"""fleetctl.deploy.files: planning writes where a parent directory is a regular file."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from fleetctl.deploy import operations as ops
from fleetctl.errors import FleetError


def test_a_file_where_a_directory_belongs_is_one_error_and_changes_nothing(
        tmp_path: Path) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    server = fleet_dir / "server"
    shutil.rmtree(server)
    server.write_text("in the way\n")
    assert ops.render_fleet(fleet_dir, dry_run=True).changes  # a preview, no traceback
    with pytest.raises(FleetError, match=r"server/\S+: cannot write: Not a directory; "
                                         r"nothing was changed"):
        ops.render_fleet(fleet_dir)
    assert server.read_text() == "in the way\n"
