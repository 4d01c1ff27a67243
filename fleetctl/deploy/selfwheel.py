"""A wheel of the running fleetctl, for images and robot bundles.

``fleetctl build`` installs fleetctl into the images and ``fleetctl export`` ships it to
robots; both must work from an installed wheel with no source checkout. Two sources:

- a checkout (an editable install, or ``--source``): ``pip wheel`` of it;
- an installed distribution: its files, listed in its ``RECORD``, repacked into a wheel
  (PEP 427: the same paths, a fresh ``RECORD`` with SHA-256 digests). pip's own install
  markers (``INSTALLER``, ``REQUESTED``, ``direct_url.json``), byte code and the console
  script (outside site-packages) are left out, as they were not in the original wheel.

Repacked wheels are reproducible (sorted members, fixed timestamps), so an unchanged
installation gives the same bytes and Docker's layer cache keeps hitting.
"""

from __future__ import annotations

import base64
import csv
import hashlib
import io
import subprocess
import sys
import zipfile
from importlib import metadata
from pathlib import Path, PurePosixPath

from fleetctl.errors import EnvironmentMissing, FleetError

DIST_NAME = "fleetctl"
_PIP_MARKERS = frozenset({"INSTALLER", "REQUESTED", "direct_url.json", "RECORD"})
_FIXED_TIME = (1980, 1, 1, 0, 0, 0)


def source_checkout() -> Path | None:
    """The checkout this fleetctl runs from (editable install), or ``None``."""
    root = Path(__file__).resolve().parents[2]
    if (root / "pyproject.toml").is_file() and (root / "fleetctl" / "__init__.py").is_file():
        return root
    return None


def wheel_name(version: str) -> str:
    """The file name of fleetctl's wheel (pure Python, any platform)."""
    return f"{DIST_NAME}-{version}-py3-none-any.whl"


def fleetctl_wheel(dest_dir: Path, source: Path | None = None) -> Path:
    """Write a wheel of the running fleetctl into *dest_dir* and return its path.

    Args:
        dest_dir: Directory for the wheel (created if missing).
        source: A checkout to build from; ``None`` uses this fleetctl's own checkout when
            it runs from one, else repacks the installed distribution.

    Raises:
        FleetError: ``pip wheel`` failed, or the installation lists no files.
    """
    dest_dir.mkdir(parents=True, exist_ok=True)
    source = source or source_checkout()
    if source is not None:
        return _pip_wheel(source, dest_dir)
    return repack_installed(dest_dir)


def _pip_wheel(source: Path, dest_dir: Path) -> Path:
    res = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(dest_dir),
         str(source)],
        capture_output=True, text=True, check=False,
    )
    if res.returncode != 0:
        raise FleetError(f"pip wheel {source} failed: {res.stderr.strip()[-300:]}")
    wheels = sorted(dest_dir.glob(f"{DIST_NAME}-*.whl"), key=lambda p: p.stat().st_mtime)
    if not wheels:
        raise FleetError(f"pip wheel {source} wrote no {DIST_NAME} wheel into {dest_dir}")
    return wheels[-1]


def _installed_files(dist: metadata.Distribution) -> list[tuple[str, Path]]:
    """(archive name, file) of every file the wheel had, from the installed RECORD."""
    out = []
    for entry in dist.files or []:
        posix = PurePosixPath(str(entry))
        if posix.parts[0] == ".." or "__pycache__" in posix.parts or posix.suffix == ".pyc":
            continue
        if posix.parent.name.endswith(".dist-info") and posix.name in _PIP_MARKERS:
            continue
        out.append((str(posix), Path(str(dist.locate_file(entry)))))
    return sorted(out)


def repack_installed(dest_dir: Path) -> Path:
    """Rebuild the installed fleetctl's wheel from its files (see the module doc).

    Raises:
        EnvironmentMissing: fleetctl is not installed as a distribution.
        FleetError: the installation lists no files, or one of them is missing.
    """
    try:
        dist = metadata.distribution(DIST_NAME)
    except metadata.PackageNotFoundError as exc:
        raise EnvironmentMissing("fleetctl is not installed (no distribution metadata)") from exc
    files = _installed_files(dist)
    if not files:
        raise FleetError("the installed fleetctl lists no files (RECORD missing)")
    dist_info = next(name.split("/")[0] for name, _ in files if ".dist-info/" in name)
    out = dest_dir / wheel_name(dist.version)
    rows: list[tuple[str, str, str]] = []
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, path in files:
            try:
                data = path.read_bytes()
            except OSError as exc:
                raise FleetError(f"installed fleetctl file {path} is unreadable: {exc}") from None
            _add(zf, name, data)
            rows.append((name, _digest(data), str(len(data))))
        rows.append((f"{dist_info}/RECORD", "", ""))
        record = io.StringIO()
        csv.writer(record, lineterminator="\n").writerows(rows)
        _add(zf, f"{dist_info}/RECORD", record.getvalue().encode())
    return out


def _add(zf: zipfile.ZipFile, name: str, data: bytes) -> None:
    info = zipfile.ZipInfo(name, date_time=_FIXED_TIME)
    info.compress_type = zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    zf.writestr(info, data)


def _digest(data: bytes) -> str:
    raw = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=")
    return "sha256=" + raw.decode()
