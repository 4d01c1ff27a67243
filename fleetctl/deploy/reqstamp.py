"""What a build directory was made from: its ``.inputs`` stamp.

The wheelhouses (``context/wheels/*``) and the ROS message build venv each keep a stamp
of their inputs, so an unchanged build reuses them. Requirements among those inputs come
spelled differently from a checkout (``pyproject.toml``) and from an installed wheel (its
metadata), so they are made canonical first (:func:`requirements_stamp`).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

STAMP_NAME = ".inputs"


def stamped_with(directory: Path, inputs: str) -> bool:
    """True when *directory* was stamped with exactly *inputs*."""
    stamp = directory / STAMP_NAME
    return stamp.is_file() and stamp.read_text() == inputs


def write_stamp(directory: Path, inputs: str) -> None:
    """Stamp *directory* with *inputs* (nothing when a failed step left no directory)."""
    if directory.is_dir():
        (directory / STAMP_NAME).write_text(inputs)


def requirements_stamp(reqs: Sequence[str]) -> str:
    """What a wheelhouse was made from, the same however the requirements were spelled.

    A checkout's ``pyproject.toml`` says ``websockets>=13,<16``; an installed wheel's
    metadata says ``websockets<16,>=13`` (and may order the list differently), so
    comparing the text made switching between a checkout build and a wheel build download
    every wheelhouse again. Names are compared as PEP 503 normalizes them, specifiers as a
    sorted set, whitespace ignored, the list sorted.
    """
    return "\n".join(sorted(_canonical_requirement(r) for r in reqs))


def _canonical_requirement(req: str) -> str:
    spec, semicolon, marker = req.partition(";")
    found = re.fullmatch(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(\[[^\]]*\])?\s*\(?([^)]*)\)?\s*",
                         spec)
    if found is None:  # not a plain name[extras] specifier: compare it as written
        return "".join(req.split())
    name = re.sub(r"[-_.]+", "-", found.group(1)).lower()
    extras = ",".join(sorted(e.strip() for e in (found.group(2) or "[]")[1:-1].split(",")
                             if e.strip()))
    specifiers = ",".join(sorted("".join(s.split()) for s in found.group(3).split(",")
                                 if s.strip()))
    return (f"{name}[{extras}]" if extras else name) + specifiers + (
        ";" + "".join(marker.split()) if semicolon else "")
