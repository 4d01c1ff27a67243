"""Pack a built message package as a wheel, laid out like PyPI's ros-jazzy message wheels.

A wheel rather than files copied into the venv: pip records every file (``pip uninstall``
removes them, ``pip list`` shows the build), and the same wheel installs into another venv
of the same Python and platform, e.g. the robot client image, with no compiler there.

Files outside site-packages go through the wheel's ``.data/data/`` directory, which pip
installs relative to the environment prefix: ``lib/*.so``, ``share/<pkg>/...``,
``share/ament_index/...`` and ``include/<pkg>/...``, where the ros-jazzy wheels put theirs.
"""

from __future__ import annotations

import base64
import hashlib
import sys
import sysconfig
import zipfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class WheelSpec:
    """Name and metadata of one wheel.

    Attributes:
        dist: distribution name, e.g. ``ros-tf2-msgs`` (the ros-jazzy wheels' pattern).
        version: PEP 440 version; the local part carries the build key.
        summary: one line.
        license: SPDX expression of the message definitions and the generated code.
        requires: ``Requires-Dist`` lines (the message packages it uses).
    """

    dist: str
    version: str
    summary: str
    license: str
    requires: Sequence[str]

    @property
    def stem(self) -> str:
        """``<dist>-<version>`` with the name normalized as wheel file names want it."""
        return f"{self.dist.replace('-', '_')}-{self.version}"

    def filename(self) -> str:
        """The wheel file name, tagged for this interpreter and platform only."""
        return f"{self.stem}-{python_tag()}-{python_tag()}-{platform_tag()}.whl"


def python_tag() -> str:
    """``cp311`` for CPython 3.11: the extension modules are built for this ABI only."""
    return f"cp{sys.version_info.major}{sys.version_info.minor}"


def platform_tag() -> str:
    """``linux_x86_64``: the libraries link this machine's glibc and the venv's ROS wheels."""
    return sysconfig.get_platform().replace("-", "_").replace(".", "_")


def write_wheel(
    spec: WheelSpec, out_dir: Path, site_files: Iterable[tuple[Path, str]],
    data_files: Iterable[tuple[Path, str]],
) -> Path:
    """Write the wheel.

    Args:
        spec: name and metadata.
        out_dir: directory for the .whl (created).
        site_files: (file, path inside site-packages) pairs.
        data_files: (file, path relative to the environment prefix) pairs.

    Returns:
        The wheel's path.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / spec.filename()
    tmp = path.with_suffix(".tmp")
    info = f"{spec.stem}.dist-info"
    data = f"{spec.stem}.data/data"
    record: list[str] = []
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
        for src, arc in sorted(site_files, key=lambda item: item[1]):
            record.append(_add(zf, arc, src.read_bytes()))
        for src, arc in sorted(data_files, key=lambda item: item[1]):
            record.append(_add(zf, f"{data}/{arc}", src.read_bytes()))
        record.append(_add(zf, f"{info}/METADATA", _metadata(spec).encode()))
        record.append(_add(zf, f"{info}/WHEEL", _wheel_file().encode()))
        record.append(f"{info}/RECORD,,")
        zf.writestr(f"{info}/RECORD", "\n".join(record) + "\n")
    tmp.replace(path)
    return path


def _add(zf: zipfile.ZipFile, arcname: str, payload: bytes) -> str:
    info = zipfile.ZipInfo(arcname, date_time=(2020, 1, 1, 0, 0, 0))
    # Executable bits for shared objects, as a compiler leaves them; 0644 for the rest.
    mode = 0o755 if arcname.endswith(".so") else 0o644
    info.external_attr = (0o100000 | mode) << 16
    info.compress_type = zipfile.ZIP_DEFLATED
    zf.writestr(info, payload)
    digest = base64.urlsafe_b64encode(hashlib.sha256(payload).digest()).rstrip(b"=").decode()
    return f"{arcname},sha256={digest},{len(payload)}"


def _metadata(spec: WheelSpec) -> str:
    lines = [
        "Metadata-Version: 2.1",
        f"Name: {spec.dist}",
        f"Version: {spec.version}",
        f"Summary: {spec.summary}",
        f"License: {spec.license}",
        *(f"Requires-Dist: {req}" for req in spec.requires),
    ]
    return "\n".join(lines) + "\n"


def _wheel_file() -> str:
    return (
        "Wheel-Version: 1.0\n"
        "Generator: fleetctl scripts/ros_msgs\n"
        "Root-Is-Purelib: false\n"
        f"Tag: {python_tag()}-{python_tag()}-{platform_tag()}\n"
    )
