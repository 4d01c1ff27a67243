"""fleetctl.deploy.files: planning writes where a parent directory is a regular file."""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

import pytest

from fleetctl.deploy import files
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


def test_a_write_that_fails_names_the_file_not_its_temp(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    before = (fleet_dir / "fleet.yaml").read_bytes()

    def refused(prefix: str, suffix: str, dir: Path) -> tuple[int, str]:
        # What a directory the operator may not write gives: the temp file's own name.
        raise PermissionError(errno.EACCES, "Permission denied",
                              str(Path(dir) / f"{prefix}17vn9af5{suffix}"))

    monkeypatch.setattr(files.tempfile, "mkstemp", refused)
    with pytest.raises(FleetError) as info:
        ops.set_endpoint(fleet_dir, "vpn.example.org:51820")
    named, _, rest = str(info.value).partition(": ")
    assert rest == "cannot write: Permission denied; nothing was changed"
    # The first file the command writes (the certificate, whose names follow the
    # endpoint), as the operator knows it.
    assert Path(named) == fleet_dir / "server/tls/cert.pem"
    assert (fleet_dir / "fleet.yaml").read_bytes() == before
