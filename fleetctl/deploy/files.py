"""Planned, atomic file changes.

Every fleet operation first computes a :class:`Plan` in memory (so bad input changes
nothing), then either previews it (``--dry-run``) or applies it. Writes are atomic (a temp
file in the same directory, fsync, rename) and skipped when the bytes and mode are already
right, so regenerating an unchanged fleet leaves every file and its mtime alone. Nothing
is written through a symlink: the temp file is created exclusively without following
links, and a symlink at the target is replaced, never followed.

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
import shutil
import stat
from dataclasses import dataclass, field
from pathlib import Path

from fleetctl.errors import ConfigError

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
    """File writes and deletions, computed before anything touches the disk."""

    writes: list[FileWrite] = field(default_factory=list)
    deletes: list[Path] = field(default_factory=list)
    directories: dict[Path, int] = field(default_factory=dict)

    def directory(self, path: Path, mode: int) -> None:
        """Make sure *path* exists with exactly *mode* (e.g. 0o700 above secret dirs)."""
        self.directories[path] = mode

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

    def preview(self) -> list[Change]:
        """Return what :meth:`apply` would do, touching nothing."""
        changes = [Change(p, ChangeKind.DELETE) for p in self.deletes if p.exists()]
        changes += [Change(w.path, _write_kind(w)) for w in self.writes]
        return changes

    def apply(self) -> list[Change]:
        """Delete, then write; return what was done, in order."""
        changes: list[Change] = []
        for path in self.deletes:
            if _remove(path):
                changes.append(Change(path, ChangeKind.DELETE))
        for path, mode in self.directories.items():
            ensure_dir(path, mode)
        for w in self.writes:
            changes.append(Change(w.path, write_file(w)))
        return changes


def _write_kind(w: FileWrite) -> ChangeKind:
    try:
        st = w.path.lstat()
    except FileNotFoundError:
        return ChangeKind.CREATE
    if not stat.S_ISREG(st.st_mode):
        return ChangeKind.UPDATE  # a symlink (or other) is replaced by a regular file
    same = stat.S_IMODE(st.st_mode) == w.mode and w.path.read_bytes() == w.data
    return ChangeKind.UNCHANGED if same else ChangeKind.UPDATE


def _same_bytes(path: Path, data: bytes) -> bool:
    """True when *path* is a regular file (not a symlink) holding exactly *data*."""
    try:
        st = path.lstat()
    except FileNotFoundError:
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


def write_file(w: FileWrite) -> ChangeKind:
    """Write one file atomically unless it already has the right bytes and mode.

    The temp file is created with the final mode (never briefly world-readable), fsynced,
    and renamed over the target, so a reader sees the old file or the new one, never half.
    """
    ensure_dir(w.path.parent, w.dir_mode)
    kind = _write_kind(w)
    if kind is ChangeKind.UNCHANGED:
        return kind
    if kind is ChangeKind.UPDATE and _same_bytes(w.path, w.data):
        w.path.chmod(w.mode)  # only the mode was wrong: keep the content and mtime
        return kind
    tmp = w.path.with_name(f".{w.path.name}.{os.getpid()}.tmp")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()  # a stale temp file (or a planted symlink): unlink never follows it
    # O_EXCL | O_NOFOLLOW: never open through a symlink someone raced into that name.
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, w.mode)
    with os.fdopen(fd, "wb") as f:
        os.fchmod(fd, w.mode)  # the umask may have narrowed the mode os.open used
        f.write(w.data)
        f.flush()
        os.fsync(fd)
    try:
        os.replace(tmp, w.path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    return kind


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
    first, _, rest = data.partition(b"\n")
    match = _STAMP.fullmatch(first.decode("utf-8", "replace").rstrip("\r"))
    if match is None:
        # Without a header: fine only if it is exactly what fleetctl would write now.
        body = new_text.partition("\n")[2].encode("utf-8")
        return "generated" if data == body else "unstamped"
    return "generated" if hashlib.sha256(rest).hexdigest() == match.group(1) else "edited"


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
    except FileNotFoundError:
        return
    state = "edited" if not stat.S_ISREG(st.st_mode) else edit_state(path.read_bytes(), new_text)
    if state == "generated":
        return
    what = ("was edited by hand" if state == "edited" else
            "has no fleetctl digest line (edited by hand, or written by an older fleetctl)")
    raise ConfigError(f"{label} {what}: {hint}, then run `fleetctl render --force` to "
                      "overwrite")
