"""``fleetctl export NAME``: a bundle with just what one robot needs (docs/robot.md).

A directory (0700, since ``wg0.conf`` holds the robot's private key) or, when the output
path ends in ``.tar.gz``, a reproducible tarball (fixed mtimes and owners, sorted members:
the same fleet, keys and wheel give the same bytes). What is in it:
:func:`fleetctl.deploy.bundle.robot_bundle`.
"""

from __future__ import annotations

import gzip
import io
import tarfile
import tempfile
from collections.abc import Callable
from pathlib import Path

from fleetctl.deploy.bundle import BundleFile, robot_bundle
from fleetctl.deploy.files import (
    SECRET_DIR_MODE,
    SECRET_FILE_MODE,
    FileWrite,
    Plan,
)
from fleetctl.deploy.fleet import fleet_file, load_fleet, require_endpoint
from fleetctl.deploy.keystore import load_robot_keys, load_server_key
from fleetctl.deploy.operations import ExportResult, finish_plan
from fleetctl.deploy.render import FleetKeys
from fleetctl.deploy.selfwheel import fleetctl_wheel
from fleetctl.errors import ConfigError

TARBALL_SUFFIX = ".tar.gz"


def default_bundle_path(name: str) -> Path:
    """Return the default output path of robot *name*'s bundle: ``./NAME-bundle``."""
    return Path(f"{name}-bundle")


def tarball(prefix: str, files: list[BundleFile]) -> bytes:
    """Return a gzipped tar of *files* under ``prefix/``, byte-for-byte reproducible."""
    raw = io.BytesIO()
    with tarfile.open(fileobj=raw, mode="w", format=tarfile.PAX_FORMAT) as tar:
        tar.addfile(_member(prefix, tarfile.DIRTYPE, SECRET_DIR_MODE, 0))
        for f in sorted(files, key=lambda f: f.relpath):
            tar.addfile(_member(f"{prefix}/{f.relpath}", tarfile.REGTYPE, f.mode, len(f.data)),
                        io.BytesIO(f.data))
    return gzip.compress(raw.getvalue(), mtime=0)


def _member(name: str, kind: bytes, mode: int, size: int) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type, info.mode, info.size = kind, mode, size
    info.mtime, info.uid, info.gid, info.uname, info.gname = 0, 0, 0, "root", "root"
    return info


WheelBuilder = Callable[[Path], Path]  # dest_dir -> a fleetctl wheel written into it


def export_robot(fleet_dir: Path, name: str, out: Path | None = None, *,
                 dry_run: bool = False, wheel: Path | None = None,
                 build_wheel: WheelBuilder = fleetctl_wheel) -> ExportResult:
    """Write robot *name*'s bundle (files: :func:`fleetctl.deploy.bundle.robot_bundle`).

    Args:
        fleet_dir: the fleet directory.
        name: the robot.
        out: a directory, or a path ending in ``.tar.gz``; default ``./NAME-bundle``.
            Files already in an existing directory are replaced, others left alone.
        dry_run: compute and return the changes without writing anything.
        wheel: the fleetctl wheel to ship; ``None`` builds one of the running fleetctl
            with *build_wheel* (a few seconds from a checkout).
        build_wheel: writes a fleetctl wheel into a directory and returns its path.

    Raises:
        ConfigError: no such robot, no keys for it yet, no endpoint in ``fleet.yaml``, or
            a malformed fleet directory.
        FleetError: the wheel could not be built.
    """
    fleet = load_fleet(fleet_dir)
    robot = fleet.robot(name)
    if robot is None:
        raise ConfigError(f"robot {name!r} is not in {fleet_file(fleet_dir)}")
    require_endpoint(fleet, fleet_dir)  # a bundle without one cannot reach the server
    robot_keys = load_robot_keys(fleet_dir, name)
    if robot_keys is None:
        raise ConfigError(f"robot {name!r} has no keys yet (run 'fleetctl render' first)")
    keys = FleetKeys(load_server_key(fleet_dir), {name: robot_keys})
    if wheel is not None:
        files = robot_bundle(fleet, robot, keys, wheel)
    else:
        with tempfile.TemporaryDirectory(prefix="fleetctl-wheel-") as tmp:
            files = robot_bundle(fleet, robot, keys, build_wheel(Path(tmp)))
    path = out if out is not None else default_bundle_path(name)
    plan = Plan()
    if path.name.endswith(TARBALL_SUFFIX):
        prefix = path.name.removesuffix(TARBALL_SUFFIX)
        # 0600 file, but the directory it lands in is the caller's: leave its mode alone.
        plan.writes.append(FileWrite(path, tarball(prefix, files), SECRET_FILE_MODE, None))
    else:
        plan.directory(path, SECRET_DIR_MODE)
        for f in files:
            # Secrets stay in a 0700 directory; the bundle directory itself is already one.
            plan.writes.append(FileWrite(path / f.relpath, f.data, f.mode,
                                         SECRET_DIR_MODE if f.secret else None))
    return ExportResult(robot, path, finish_plan(plan, path, dry_run))
