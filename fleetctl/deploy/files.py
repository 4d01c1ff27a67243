"""Planned, atomic file changes.

Every fleet operation first computes a :class:`Plan` in memory (so bad input changes
nothing), then either previews it (``--dry-run``) or applies it. Applying is all or
nothing across every file of the plan (:meth:`Plan.apply`); each write is atomic (a temp
file in the same directory, fsync, rename) and skipped when the bytes and mode are already
right, so regenerating an unchanged fleet leaves every file and its mtime alone. Nothing
is written through a symlink: temp files get random names and are created exclusively
without following links (``mkstemp``), and a symlink at the target is replaced, never
followed.

Generated files carry a first line ``# fleetctl: generated, sha256=HEX`` (an HTML comment
in Markdown) where HEX is the SHA-256 of everything after that line. A file whose rest no
longer matches was edited by hand; :func:`check_overwrite` refuses to replace it.
"""

from __future__ import annotations

import contextlib
import enum
import hashlib
import os
import re
import secrets
import shutil
import stat
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from fleetctl.errors import ConfigError, ExitCode, FleetError

SECRET_FILE_MODE = 0o600
SECRET_DIR_MODE = 0o700
PUBLIC_FILE_MODE = 0o644
PUBLIC_DIR_MODE = 0o755


class ChangeKind(enum.Enum):
    """What applying a plan does (or did) to one path."""

    CREATE = "create"
    UPDATE = "update"
    UNCHANGED = "unchanged"
    DELETE = "delete"


@dataclass(frozen=True)
class FileWrite:
    """One file to write.

    Attributes:
        path: the file.
        data: its full content (may hold keys, so it is left out of the repr).
        mode: permission bits of the file, e.g. 0o600.
        dir_mode: permission bits forced on the file's directory (0o700 for secrets);
            ``None`` leaves an existing directory alone and creates a missing one 0o755.
    """

    path: Path
    data: bytes = field(repr=False)
    mode: int = PUBLIC_FILE_MODE
    dir_mode: int | None = None


@dataclass(frozen=True)
class Change:
    """The effect of a plan on one path."""

    path: Path
    kind: ChangeKind


@dataclass
class Plan:
    """File writes and deletions, computed before anything touches the disk.

    :meth:`apply` is all or nothing: every new file is first written in full to a temp
    file beside its target (so a full disk or a permission error is met before anything
    is replaced), then the temp files are renamed over their targets; if any step fails,
    every step already taken is undone (replaced files come back from hard-linked
    backups, deleted ones from where they were moved aside, created directories are
    removed), so the directory is as it was and running the command again works.
    """

    writes: list[FileWrite] = field(default_factory=list)
    deletes: list[Path] = field(default_factory=list)
    directories: dict[Path, int] = field(default_factory=dict)
    new_directories: dict[Path, int] = field(default_factory=dict)
    # The directory the plan writes in (the fleet directory, a bundle): a symbolic link
    # below it, on the way to a file, is refused (see refuse_linked_directories).
    root: Path | None = None

    def directory(self, path: Path, mode: int) -> None:
        """Make sure *path* exists with exactly *mode* (e.g. 0o700 above secret dirs).

        Only for directories fleetctl owns (inside the fleet directory): an existing one
        gets *mode* forced on it.
        """
        self.directories[path] = mode

    def new_directory(self, path: Path, mode: int) -> None:
        """Create *path* with *mode* if it is missing; an existing directory (someone
        else's, e.g. an ``export --out`` target) keeps its mode."""
        self.new_directories[path] = mode

    def write(self, path: Path, data: bytes | str, *, secret: bool = False) -> None:
        """Add a write; *secret* files are 0600 in a 0700 directory."""
        raw = data.encode("utf-8") if isinstance(data, str) else data
        if secret:
            self.writes.append(FileWrite(path, raw, SECRET_FILE_MODE, SECRET_DIR_MODE))
        else:
            self.writes.append(FileWrite(path, raw, PUBLIC_FILE_MODE, None))

    def delete(self, path: Path) -> None:
        """Add a deletion of a file or a whole directory tree (missing is fine)."""
        self.deletes.append(path)

    def check_directories(self) -> None:
        """Refuse a symbolic link below :attr:`root` on the way to a file or directory of
        the plan (what :meth:`preview` and :meth:`apply` do first).

        Raises:
            ConfigError: naming the link.
        """
        if self.root is None:
            return
        for path in (*(w.path.parent for w in self.writes), *self.directories,
                     *self.new_directories, *(p.parent for p in self.deletes)):
            refuse_linked_directories(self.root, path)

    def preview(self) -> list[Change]:
        """Return what :meth:`apply` would do, touching nothing."""
        self.check_directories()
        changes = [Change(p, ChangeKind.DELETE) for p in self.deletes if _exists(p)]
        changes += [Change(w.path, kind) for w, kind in zip(self.writes, self.write_kinds(),
                                                            strict=True)]
        return changes

    def write_kinds(self) -> list[ChangeKind]:
        """What each write does, in order: a file under (or at) a path the plan deletes is
        created anew whatever is there now, since the deletion comes first (``init
        --force`` deletes ``server/`` and writes ``server/server.yaml`` again: judged
        against the old file it was "unchanged", so it was never written and the
        deletion took it)."""
        deleted = [p for p in self.deletes if _exists(p)]
        return [ChangeKind.CREATE if any(w.path.is_relative_to(d) for d in deleted)
                else _write_kind(w) for w in self.writes]

    def apply(self) -> list[Change]:
        """Delete, then write, all or nothing; return what was done, in order.

        Raises:
            WriteFailed: a file or directory could not be written (disk full, permission
                denied, ...): naming it; everything done so far has been undone.
        """
        self.check_directories()
        tx = _Transaction()
        try:
            changes = tx.run(self)
        except OSError as exc:
            tx.rollback()
            raise WriteFailed.from_os_error(exc) from None
        except BaseException:
            tx.rollback()
            raise
        tx.finish()
        return changes


def refuse_linked_directories(root: Path, directory: Path) -> None:
    """Refuse *directory* when it, or a directory between *root* and it, is a symbolic
    link: a file written there would land wherever the link points (a robot's private key
    in someone else's directory), and forcing 0700 on it would change the mode of a
    directory fleetctl does not own. *root* itself may be a link (a fleet directory
    reached through one); a *directory* outside *root* is not checked.

    Raises:
        ConfigError: naming the link and where it points.
    """
    try:
        parts = directory.relative_to(root).parts
    except ValueError:
        return
    current = root
    for part in parts:
        current = current / part
        if current.is_symlink():
            raise ConfigError(f"{current} is a symbolic link (to {os.readlink(current)}), "
                              "which fleetctl never writes through: make it a directory of "
                              "its own (or remove it and let fleetctl make it)")


class WriteFailed(FleetError):
    """A file could not be written; the directory was left as it was."""

    exit_code = ExitCode.ENVIRONMENT

    @classmethod
    def from_os_error(cls, exc: OSError) -> WriteFailed:
        """One line naming the file and the reason (e.g. ``No space left on device``)."""
        where = f"{exc.filename}: " if exc.filename else ""
        return cls(f"{where}cannot write: {exc.strerror or exc}; nothing was changed")


def write_all(fd: int, data: bytes) -> None:
    """Write all of *data* to the file descriptor *fd*.

    The one primitive every file's content goes through (tests inject failures here).
    """
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def rename(src: Path, dst: Path) -> None:
    """Rename *src* over *dst* atomically (the primitive every commit goes through)."""
    os.replace(src, dst)


@contextlib.contextmanager
def _named(target: Path) -> Iterator[None]:
    """An OSError while writing *target* names *target*: the operator's file, not the
    random temp or backup name beside it where the failure happened
    (``fleet.yaml: cannot write: ...``, not ``.fleet.yaml.17vn9af5.tmp: ...``). A failure
    on a directory on the way keeps naming that directory."""
    try:
        yield
    except OSError as exc:
        if exc.filename is not None and Path(exc.filename) in (target.parent,
                                                               *target.parent.parents):
            raise
        raise OSError(exc.errno, exc.strerror or str(exc), str(target)) from exc


def _exists(path: Path) -> bool:
    return os.path.lexists(path)


def _aside_name(path: Path, what: str) -> Path:
    """A fresh hidden name beside *path* (random: nobody can plant something there first)."""
    return path.with_name(f".{path.name}.{what}-{secrets.token_hex(6)}")


@dataclass
class _Transaction:
    """The steps of one :meth:`Plan.apply`, each with its undo."""

    undo: list[Callable[[], object]] = field(default_factory=list)
    temps: list[Path] = field(default_factory=list)
    garbage: list[Path] = field(default_factory=list)  # removed once everything succeeded

    def run(self, plan: Plan) -> list[Change]:
        changes = [Change(p, ChangeKind.DELETE) for p in plan.deletes if _exists(p)]
        kinds = plan.write_kinds()
        for change in changes:
            self._move_aside(change.path)
        for path, mode in plan.directories.items():
            self._directory(path, mode, force=True)
        for path, mode in plan.new_directories.items():
            self._directory(path, mode, force=False)
        staged = []
        for w, kind in zip(plan.writes, kinds, strict=True):
            with _named(w.path):
                staged.append(self._stage(w, kind))
        for w, temp in zip(plan.writes, staged, strict=True):
            if temp is not None:
                with _named(w.path):
                    self._commit(temp, w.path)
        return changes + [Change(w.path, kind) for w, kind in zip(plan.writes, kinds,
                                                                  strict=True)]

    def rollback(self) -> None:
        """Undo every step taken, newest first (best effort: each step on its own)."""
        self._cleanup(self.temps)  # first: a directory to remove must be empty
        for step in reversed(self.undo):
            with contextlib.suppress(OSError):
                step()

    def finish(self) -> None:
        """Drop the backups and what was deleted (after every step succeeded)."""
        self._cleanup(self.temps + self.garbage)

    @staticmethod
    def _cleanup(paths: list[Path]) -> None:
        for path in paths:
            with contextlib.suppress(OSError):
                _remove(path)

    def _move_aside(self, path: Path) -> None:
        aside = _aside_name(path, "deleted")
        rename(path, aside)
        self.undo.append(lambda: rename(aside, path))
        self.garbage.append(aside)

    def _directory(self, path: Path, mode: int | None, *, force: bool) -> None:
        """Create *path* and its missing parents (0755; *path* itself *mode*)."""
        missing = [p for p in (path, *path.parents) if not _exists(p)]
        for p in reversed(missing):
            p.mkdir(PUBLIC_DIR_MODE if p != path or mode is None else mode)
            self.undo.append(p.rmdir)
            if p == path and mode is not None:
                p.chmod(mode)  # the umask may have narrowed it
        if force and not missing and mode is not None:
            self._chmod(path, mode)

    def _chmod(self, path: Path, mode: int) -> None:
        old = stat.S_IMODE(path.stat().st_mode)
        if old != mode:
            path.chmod(mode)
            self.undo.append(lambda: path.chmod(old))

    def _stage(self, w: FileWrite, kind: ChangeKind) -> Path | None:
        """Write *w* to a temp file beside it (None: nothing to write)."""
        self._directory(w.path.parent, w.dir_mode, force=w.dir_mode is not None)
        if kind is ChangeKind.UNCHANGED:
            return None
        if kind is ChangeKind.UPDATE and _same_bytes(w.path, w.data):
            self._chmod(w.path, w.mode)  # only the mode was wrong: keep content and mtime
            return None
        # mkstemp: a random name opened O_CREAT | O_EXCL | O_NOFOLLOW, 0600 from the start,
        # so nothing planted beside the target is ever opened or followed.
        fd, name = tempfile.mkstemp(prefix=f".{w.path.name}.", suffix=".tmp",
                                    dir=w.path.parent)
        temp = Path(name)
        self.temps.append(temp)
        with contextlib.closing(_Fd(fd)):
            os.fchmod(fd, w.mode)
            write_all(fd, w.data)
            os.fsync(fd)
        return temp

    def _commit(self, temp: Path, target: Path) -> None:
        if _exists(target):
            backup = _aside_name(target, "old")
            try:
                os.link(target, backup, follow_symlinks=False)  # readers never miss it
            except OSError:
                rename(target, backup)  # no hard link here: briefly missing, still undoable
            self.garbage.append(backup)
            self.undo.append(lambda: _restore(backup, target))
        else:
            self.undo.append(lambda: _remove(target))
        rename(temp, target)


def _restore(backup: Path, target: Path) -> None:
    """Put *backup* back at *target* (a rename; or, when both still name the same file
    because the commit never happened, drop the backup: rename would do nothing)."""
    b, t = backup.lstat(), target.lstat()
    if (b.st_dev, b.st_ino) == (t.st_dev, t.st_ino):
        backup.unlink()
    else:
        rename(backup, target)


@dataclass(frozen=True)
class _Fd:
    fd: int

    def close(self) -> None:
        os.close(self.fd)


def _write_kind(w: FileWrite) -> ChangeKind:
    try:
        st = w.path.lstat()
    except (FileNotFoundError, NotADirectoryError):  # a parent is a file: missing too
        return ChangeKind.CREATE
    if not stat.S_ISREG(st.st_mode):
        return ChangeKind.UPDATE  # a symlink (or other) is replaced by a regular file
    same = stat.S_IMODE(st.st_mode) == w.mode and w.path.read_bytes() == w.data
    return ChangeKind.UNCHANGED if same else ChangeKind.UPDATE


def _same_bytes(path: Path, data: bytes) -> bool:
    """True when *path* is a regular file (not a symlink) holding exactly *data*."""
    try:
        st = path.lstat()
    except (FileNotFoundError, NotADirectoryError):  # a parent is a file: missing too
        return False
    return stat.S_ISREG(st.st_mode) and path.read_bytes() == data


def _remove(path: Path) -> bool:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
        return True
    try:
        path.unlink()
    except FileNotFoundError:
        return False
    return True


def ensure_dir(path: Path, mode: int | None) -> None:
    """Create *path* (and missing parents, 0755); force *mode* on it if given."""
    path.mkdir(mode=PUBLIC_DIR_MODE if mode is None else mode, parents=True, exist_ok=True)
    if mode is not None and stat.S_IMODE(path.stat().st_mode) != mode:
        path.chmod(mode)


def write_file(w: FileWrite, root: Path | None = None) -> ChangeKind:
    """Write one file atomically unless it already has the right bytes and mode.

    The temp file is created with a random name, exclusively, without following links,
    with the final mode (never briefly world-readable); it is fsynced and renamed over
    the target, so a reader sees the old file or the new one, never half.

    Raises:
        ConfigError: a directory below *root* on the way to it is a symbolic link.
        WriteFailed: it could not be written (nothing changed).
    """
    return Plan(writes=[w], root=root).apply()[0].kind


# --- generated-file stamps -------------------------------------------------------------

STAMP_PREFIX = "fleetctl: generated, sha256="
_STAMP = re.compile(r"(?:# |<!-- )fleetctl: generated, sha256=([0-9a-f]{64})(?: -->)?")


def stamp(body: str, *, markdown: bool = False) -> str:
    """Return *body* with its digest line first (an HTML comment when *markdown*)."""
    digest = hashlib.sha256(body.encode("utf-8")).hexdigest()
    line = f"<!-- {STAMP_PREFIX}{digest} -->" if markdown else f"# {STAMP_PREFIX}{digest}"
    return f"{line}\n{body}"


def edit_state(data: bytes, new_text: str) -> str:
    """Say whether a generated file's current bytes may be replaced by *new_text*.

    Returns:
        ``"generated"``: untouched since fleetctl wrote it (its digest matches);
        ``"edited"``: it carries a digest line, but the rest no longer matches it;
        ``"unstamped"``: no digest line, and not what fleetctl would write now.
    """
    if data == new_text.encode("utf-8"):
        return "generated"
    matches = _stamp_matches(data)
    if matches is None:
        # Without a header: fine only if it is exactly what fleetctl would write now.
        body = new_text.partition("\n")[2].encode("utf-8")
        return "generated" if data == body else "unstamped"
    return "generated" if matches else "edited"


def is_untouched(data: bytes) -> bool:
    """True when *data* carries fleetctl's digest line and still matches it: a generated
    file nobody edited, which fleetctl may delete without losing anyone's work."""
    return _stamp_matches(data) is True


def _stamp_matches(data: bytes) -> bool | None:
    """Whether the rest of *data* matches its digest line; None without one."""
    first, _, rest = data.partition(b"\n")
    match = _STAMP.fullmatch(first.decode("utf-8", "replace").rstrip("\r"))
    if match is None:
        return None
    return hashlib.sha256(rest).hexdigest() == match.group(1)


def check_overwrite(path: Path, new_text: str, label: str, hint: str) -> None:
    """Refuse to replace the generated file *path* if someone edited it.

    Args:
        path: the file (missing is fine).
        new_text: what would be written (stamped).
        label: how the error names the file.
        hint: where the setting belongs instead, e.g. ``put topics in fleet.yaml ...``.

    Raises:
        ConfigError: one line naming the file, where the setting belongs and the fix.
    """
    try:
        st = path.lstat()
    except (FileNotFoundError, NotADirectoryError):  # a parent is a file: missing too
        return
    if not stat.S_ISREG(st.st_mode):
        # Said as it is: "edited by hand" sends the operator looking for an edit.
        kind = "a symbolic link" if stat.S_ISLNK(st.st_mode) else "not a regular file"
        raise ConfigError(f"{label} is {kind}, which fleetctl never writes through: "
                          f"{hint}, then run `fleetctl render --force` to replace it")
    state = edit_state(path.read_bytes(), new_text)
    if state == "generated":
        return
    what = ("was edited by hand" if state == "edited" else
            "has no fleetctl digest line (edited by hand, or written by an older fleetctl)")
    raise ConfigError(f"{label} {what}: {hint}, then run `fleetctl render --force` to "
                      "overwrite")
