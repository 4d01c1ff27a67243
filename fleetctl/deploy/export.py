"""``fleetctl export NAME``: a bundle with just what one robot needs.

A directory (0700, since ``wg0.conf`` holds the robot's private key) or, when the output
path ends in ``.tar.gz``, a reproducible tarball (fixed mtimes and owners, sorted members:
the same fleet and keys give the same bytes).
"""

from __future__ import annotations

import gzip
import io
import tarfile
from pathlib import Path

from fleetctl.deploy.files import (
    PUBLIC_FILE_MODE,
    SECRET_DIR_MODE,
    SECRET_FILE_MODE,
    FileWrite,
    Plan,
)
from fleetctl.deploy.fleet import fleet_file, load_fleet
from fleetctl.deploy.keystore import load_robot_keys, load_server_key
from fleetctl.deploy.operations import ExportResult, finish_plan
from fleetctl.deploy.render import Artifact, FleetKeys, robot_bundle
from fleetctl.errors import ConfigError

TARBALL_SUFFIX = ".tar.gz"


def default_bundle_path(name: str) -> Path:
    """Return the default output path of robot *name*'s bundle: ``./NAME-bundle``."""
    return Path(f"{name}-bundle")


def tarball(prefix: str, artifacts: list[Artifact]) -> bytes:
    """Return a gzipped tar of *artifacts* under ``prefix/``, byte-for-byte reproducible."""
    raw = io.BytesIO()
    with tarfile.open(fileobj=raw, mode="w", format=tarfile.PAX_FORMAT) as tar:
        tar.addfile(_member(prefix, tarfile.DIRTYPE, SECRET_DIR_MODE, 0))
        for a in sorted(artifacts, key=lambda a: a.relpath):
            data = a.text.encode("utf-8")
            mode = SECRET_FILE_MODE if a.secret else PUBLIC_FILE_MODE
            tar.addfile(_member(f"{prefix}/{a.relpath}", tarfile.REGTYPE, mode, len(data)),
                        io.BytesIO(data))
    return gzip.compress(raw.getvalue(), mtime=0)


def _member(name: str, kind: bytes, mode: int, size: int) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type, info.mode, info.size = kind, mode, size
    info.mtime, info.uid, info.gid, info.uname, info.gname = 0, 0, 0, "root", "root"
    return info


def export_robot(fleet_dir: Path, name: str, out: Path | None = None, *,
                 dry_run: bool = False) -> ExportResult:
    """Write robot *name*'s bundle: ``wg0.conf``, ``client.yaml`` and a ``README.md``.

    Args:
        fleet_dir: the fleet directory.
        name: the robot.
        out: a directory, or a path ending in ``.tar.gz``; default ``./NAME-bundle``.
            Files already in an existing directory are replaced, others left alone.
        dry_run: compute and return the changes without writing anything.

    Raises:
        ConfigError: no such robot, no keys for it yet, or a malformed fleet directory.
    """
    fleet = load_fleet(fleet_dir)
    robot = fleet.robot(name)
    if robot is None:
        raise ConfigError(f"robot {name!r} is not in {fleet_file(fleet_dir)}")
    robot_keys = load_robot_keys(fleet_dir, name)
    if robot_keys is None:
        raise ConfigError(f"robot {name!r} has no keys yet (run 'fleetctl render' first)")
    artifacts = robot_bundle(fleet, robot, FleetKeys(load_server_key(fleet_dir),
                                                     {name: robot_keys}))
    path = out if out is not None else default_bundle_path(name)
    plan = Plan()
    if path.name.endswith(TARBALL_SUFFIX):
        prefix = path.name.removesuffix(TARBALL_SUFFIX)
        # 0600 file, but the directory it lands in is the caller's: leave its mode alone.
        plan.writes.append(FileWrite(path, tarball(prefix, artifacts), SECRET_FILE_MODE, None))
    else:
        plan.directory(path, SECRET_DIR_MODE)
        for a in artifacts:
            plan.write(path / a.relpath, a.text, secret=a.secret)
    return ExportResult(robot, path, finish_plan(plan, path, dry_run))
