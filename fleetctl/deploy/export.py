"""``fleetctl export NAME``: a bundle with just what one robot needs (docs/robot.md).

A directory (made 0700, since ``wg0.conf`` holds the robot's private key; an existing
directory keeps its mode, ``wg0.conf`` in it is 0600) or, when the output path ends in
``.tar.gz`` or ``.tgz``, a reproducible tarball (0600; fixed mtimes and owners, sorted
members: the same fleet, keys and wheel give the same bytes). Written like every fleet
file: all or nothing, through temp files with random names opened ``O_EXCL |
O_NOFOLLOW``. What is in it: :func:`fleetctl.deploy.bundle.robot_bundle`.
"""

from __future__ import annotations

import gzip
import io
import stat
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
    WriteFailed,
    edit_state,
)
from fleetctl.deploy.fleet import fleet_file, load_fleet, require_endpoint
from fleetctl.deploy.keystore import load_server_key
from fleetctl.deploy.operations import ExportResult, existing_robot_keys, finish_plan
from fleetctl.deploy.render import FleetKeys
from fleetctl.deploy.selfwheel import fleetctl_wheel
from fleetctl.deploy.yamlnodes import shown
from fleetctl.errors import ConfigError, ConflictError, ExitCode, FleetError
from fleetctl.smallfile import MAX_CONFIG_BYTES, read_small

TARBALL_SUFFIXES = (".tar.gz", ".tgz")
# Archive names export does not write: a new --out ending in one is refused, not made a
# directory called husky1.zip.
OTHER_ARCHIVE_SUFFIXES = (".tar", ".zip", ".tar.xz", ".txz", ".tar.bz2", ".tbz2", ".tbz",
                          ".tar.zst", ".tzst", ".tar.lz", ".7z", ".gz", ".xz", ".bz2", ".zst")


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
        out: a directory, or a path ending in ``.tar.gz`` or ``.tgz``; default
            ``./NAME-bundle``. In an existing directory the files of an earlier export
            are replaced (only those, see :func:`check_replaceable`), others left alone,
            the directory's mode too.
        dry_run: compute and return the changes without writing anything.
        wheel: the fleetctl wheel to ship; ``None`` builds one of the running fleetctl
            with *build_wheel* (a few seconds from a checkout).
        build_wheel: writes a fleetctl wheel into a directory and returns its path.

    Raises:
        ConfigError: no such robot, no keys for it yet, no endpoint in ``fleet.yaml``, or
            a malformed fleet directory.
        ConflictError: *out* exists and is the wrong kind of file, or a file of the
            bundle exists in it and was not written by an earlier export as it is.
        WriteFailed: *out* could not be written (nothing was left behind).
        FleetError: the wheel could not be built.
    """
    fleet = load_fleet(fleet_dir)
    robot = fleet.robot(name)
    if robot is None:
        raise ConfigError(f"robot {shown(name)} is not in {fleet_file(fleet_dir)}")
    path = out if out is not None else default_bundle_path(name)
    check_out_path(path)
    require_endpoint(fleet, fleet_dir)  # a bundle without one cannot reach the server
    # As render reads them: a lost key whose wg0.conf was made is "restore it from a
    # backup", not "run render", which then refused with that.
    robot_keys = existing_robot_keys(fleet_dir, name)
    if robot_keys is None:
        raise ConfigError(f"robot {name!r} has no keys yet (run 'fleetctl render' first)")
    keys = FleetKeys(load_server_key(fleet_dir), {name: robot_keys})
    if wheel is not None:
        files = robot_bundle(fleet, robot, keys, wheel)
    else:
        with tempfile.TemporaryDirectory(prefix="fleetctl-wheel-") as tmp:
            files = robot_bundle(fleet, robot, keys, build_wheel(Path(tmp)))
    plan = Plan()
    suffix = tarball_suffix(path)
    # The changes are listed relative to this: the bundle directory, or the directory the
    # tarball lands in (relative to the tarball itself it was listed as "create .").
    root = path if suffix is None else path.parent
    if suffix is not None:
        # 0600 file, but the directory it lands in is the caller's: leave its mode alone.
        plan.writes.append(FileWrite(path, tarball(path.name.removesuffix(suffix), files),
                                     SECRET_FILE_MODE, None))
    else:
        # Made 0700 when missing; an existing directory is the caller's and keeps its mode
        # (wg0.conf itself is 0600 either way).
        check_replaceable(path, files)
        plan.new_directory(path, SECRET_DIR_MODE)
        for f in files:
            plan.writes.append(FileWrite(path / f.relpath, f.data, f.mode, None))
    try:
        outcome = finish_plan(plan, root, dry_run)
    except WriteFailed as exc:
        raise WriteFailed(f"--out {path}: {exc}") from None
    return ExportResult(robot, path, outcome)


def tarball_suffix(path: Path) -> str | None:
    """Return the tarball suffix *path* ends in (``.tar.gz``, ``.tgz``, in any case, as
    written), else ``None``."""
    return next((path.name[-len(s):] for s in TARBALL_SUFFIXES
                 if path.name.lower().endswith(s)), None)


def check_replaceable(directory: Path, files: list[BundleFile]) -> None:
    """Refuse to replace a file in *directory* that an earlier export did not write.

    ``--out .`` or ``--out ~/robots`` (or an ``--out "$DIR"`` left empty: the current
    directory) replaced the operator's own ``README.md`` or ``compose.yaml`` there without
    a word. A file may be replaced when it is what fleetctl wrote (its digest line still
    matches, or it is the same bytes) or, the one file without a digest line, the wheel.

    Raises:
        ConflictError: naming the first such file (exit 4).
    """
    for f in files:
        target = directory / f.relpath
        try:
            st = target.lstat()
        except (FileNotFoundError, NotADirectoryError):
            continue
        if stat.S_ISREG(st.st_mode) and (
                f.relpath.endswith(".whl") or _written_by_export(target, f.data)):
            continue
        raise ConflictError(
            f"--out {directory}: {target} exists and is not a file of an earlier export "
            "(edited, or not fleetctl's): export into a new or empty directory, or move it "
            "away first")


def _written_by_export(path: Path, new: bytes) -> bool:
    try:
        data = read_small(path, max(len(new), MAX_CONFIG_BYTES), follow_symlinks=False)
    except OSError:
        return False
    # Untouched since an export wrote it (its digest line matches), or, without one (a
    # compose.yaml of a bundle exported before it carried one), what export writes now.
    return edit_state(data, new.decode("utf-8", "replace")) == "generated"


def check_out_path(path: Path) -> None:
    """Refuse an ``--out`` that is the wrong kind of thing already.

    Raises:
        FleetError: (usage, exit 2) a new *path* named as an archive export does not
            write (``.zip``, ``.tar``, ``.tar.xz``, ...).
        ConfigError: the directory *path* would be made in does not exist.
        ConflictError: a directory bundle onto an existing non-directory, or a tarball
            onto an existing directory (or other non-file).
    """
    parent = path.absolute().parent
    if not parent.is_dir():
        # Not made like `mkdir -p`: a typo in the path would leave the robot's private key
        # in a directory tree nobody meant to make.
        raise ConfigError(f"--out {path}: directory {parent} does not exist")
    try:
        st = path.lstat()
    except FileNotFoundError:
        other = next((s for s in OTHER_ARCHIVE_SUFFIXES if path.name.lower().endswith(s)),
                     None)
        if other is not None and tarball_suffix(path) is None:
            raise FleetError(f"--out {path}: export writes a directory or a .tar.gz / .tgz "
                             f"tarball, not a {other} archive (it would have been a "
                             f"directory named {path.name})",
                             exit_code=ExitCode.USAGE) from None
        return
    except OSError as exc:
        raise ConfigError(f"--out {path}: {exc.strerror}") from None
    if tarball_suffix(path) is None and not stat.S_ISDIR(st.st_mode):
        raise ConflictError(f"--out {path}: exists and is not a directory (give a new or "
                            "existing directory, or a path ending in .tar.gz or .tgz)")
    if tarball_suffix(path) is not None and not stat.S_ISREG(st.st_mode):
        raise ConflictError(f"--out {path}: exists and is not a regular file (a tarball "
                            "replaces only a file)")
