"""fleetctl.server.recording.files: reading recordings that are short, open or not MCAP."""

from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.errors import FleetError
from fleetctl.server.recording import files

MAGIC = b"\x89MCAP0\r\n"


@pytest.mark.parametrize("data", [b"tok\n", b"x", b"not an mcap file at all"])
def test_a_file_that_is_not_mcap_is_named(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "r.mcap"
    path.write_bytes(data)
    with pytest.raises(FleetError, match=r"r\.mcap: not an MCAP file"):
        list(files.read_messages(path))


@pytest.mark.parametrize("data", [b"", MAGIC[:3], MAGIC, MAGIC + b"\x01\x02"])
def test_a_file_cut_short_has_no_messages_yet(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "r.mcap"
    path.write_bytes(data)
    assert list(files.read_messages(path)) == []


def test_scan_skips_what_is_not_a_regular_file(tmp_path: Path) -> None:
    (tmp_path / "dir.mcap").mkdir()
    (tmp_path / "r.mcap").write_bytes(MAGIC)
    assert [f.name for f in files.scan(tmp_path)] == ["r.mcap"]


def test_scan_of_a_file_is_named(tmp_path: Path) -> None:
    (tmp_path / "afile").write_text("x")
    with pytest.raises(FleetError, match=r"afile: not a directory"):
        files.scan(tmp_path / "afile")
    assert files.scan(tmp_path / "missing") == []
