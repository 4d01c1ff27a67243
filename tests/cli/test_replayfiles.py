"""Which files ``fleetctl replay`` plays for a path: a file, or a rosbag2 bag directory."""

from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.cli.replayfiles import recording_files
from fleetctl.errors import FleetError


def _bag(tmp_path: Path, *names: str) -> Path:
    bag = tmp_path / "bag"
    bag.mkdir()
    for name in names:
        (bag / name).write_bytes(b"")
    return bag


def test_a_file_is_itself(tmp_path: Path) -> None:
    (tmp_path / "rec.mcap").write_bytes(b"")
    assert recording_files(tmp_path / "rec.mcap") == [tmp_path / "rec.mcap"]
    with pytest.raises(FleetError, match="no such recording file"):
        recording_files(tmp_path / "missing.mcap")


def test_a_bags_files_in_the_order_its_metadata_lists_them(tmp_path: Path) -> None:
    bag = _bag(tmp_path, "b_0.mcap", "a_1.mcap", "outside.mcap")
    (tmp_path / "x.mcap").write_bytes(b"")
    (bag / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  relative_file_paths: [b_0.mcap, a_1.mcap, "
        "gone.mcap, ../x.mcap, notes.txt]\n")
    assert recording_files(bag) == [bag / "b_0.mcap", bag / "a_1.mcap"]


@pytest.mark.parametrize("metadata", [None, "not: [yaml", "rosbag2_bagfile_information: 3\n"])
def test_without_usable_metadata_by_their_number(tmp_path: Path, metadata: str | None) -> None:
    bag = _bag(tmp_path, "rec_10.mcap", "rec_9.mcap", "rec_0.mcap", "rec.db3")
    if metadata is not None:
        (bag / "metadata.yaml").write_text(metadata)
    assert [p.name for p in recording_files(bag)] == ["rec_0.mcap", "rec_9.mcap",
                                                       "rec_10.mcap"]
