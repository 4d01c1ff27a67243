"""Which MCAP files ``fleetctl replay`` plays: one file, or a rosbag2 bag directory.

``ros2 bag record -s mcap`` writes a directory: ``metadata.yaml`` and ``NAME_0.mcap``,
``NAME_1.mcap``... (split by size or duration), in time order. Its files are played one
after another as one recording, in the order ``metadata.yaml`` lists them
(``rosbag2_bagfile_information.relative_file_paths``); without a usable one, by their
number (``_10`` after ``_9``). The metadata's other fields are not needed: every MCAP
file carries its own schemas and channels.
"""

from __future__ import annotations

import re
from pathlib import Path

import yaml

from fleetctl.errors import FleetError
from fleetctl.server.recording.files import SUFFIX
from fleetctl.smallfile import read_small_text
from fleetctl.yamlfile import safe_load

METADATA = "metadata.yaml"
_NUMBER = re.compile(r"(\d+)")


def recording_files(path: Path) -> list[Path]:
    """The MCAP files to play for *path*, in order.

    Raises:
        FleetError: *path* does not exist, or is a directory without a ``.mcap`` file.
    """
    if not path.is_dir():
        if not path.is_file():
            raise FleetError(f"{path}: no such recording file")
        return [path]
    listed = _listed(path)
    found = listed if listed else sorted((p for p in path.iterdir()
                                          if p.suffix == SUFFIX and p.is_file()),
                                         key=_natural)
    if not found:
        raise FleetError(f"{path}: no {SUFFIX} file in this directory (replay takes an MCAP "
                         "file, or a rosbag2 bag recorded with `-s mcap`; a .db3 bag "
                         "converts with rosbags-convert)")
    return found


def _listed(bag: Path) -> list[Path]:
    """The ``.mcap`` files ``metadata.yaml`` lists that are in *bag*; ``[]`` when it is
    missing, unreadable or lists none (the directory's own files are used then)."""
    try:
        info = safe_load(read_small_text(bag / METADATA))
        names = info["rosbag2_bagfile_information"]["relative_file_paths"]
    except (OSError, UnicodeDecodeError, yaml.YAMLError, RecursionError, KeyError,
            TypeError):
        return []
    if not isinstance(names, list):
        return []
    # Only plain names: a listed "../x.mcap" must not play a file outside the bag.
    files = [bag / n for n in names if isinstance(n, str) and "/" not in n]
    return [f for f in files if f.suffix == SUFFIX and f.is_file()]


def _natural(path: Path) -> list[object]:
    """Sort key: digits as numbers (``rec_10.mcap`` after ``rec_9.mcap``)."""
    return [int(part) if part.isdigit() else part for part in _NUMBER.split(path.name)]
