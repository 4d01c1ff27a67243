"""fleetctl.server.recording.files: reading recordings that are short, open or not MCAP."""

from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.errors import FleetError
from fleetctl.server.recording import files
from tests.server.recording.damaged import damaged_recording

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


def test_a_damaged_chunk_is_named_after_the_messages_before_it(tmp_path: Path) -> None:
    # A chunk that does not decompress is damage, not the end of what was written: it was
    # zstandard's traceback from `recordings list` on an unfinished file.
    path = tmp_path / "rec.mcap"
    first = damaged_recording(path)
    read = []
    with pytest.raises(files.DamagedRecording) as caught:
        for _schema, _channel, message in files.read_messages(path):
            read.append(message.sequence)
    assert read == list(range(first))
    assert str(caught.value).startswith(
        f"{path}: damaged data, the rest of the file cannot be read (ZstdError: ")


def test_an_unfinished_damaged_file_is_one_error_from_describe(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    damaged_recording(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # no summary, no footer: read record by record
    assert not files.is_complete(path)
    with pytest.raises(FleetError, match="damaged data"):
        files.describe(path)
