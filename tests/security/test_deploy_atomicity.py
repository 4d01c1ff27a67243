"""Fleet commands are all or nothing across every file they write (issue 14).

Each command is run once to count the files it writes, then again with the Nth write
(or the Nth rename) failing with ``ENOSPC``, for every N: the command fails with one
line naming the file, the fleet directory is exactly as before (paths, kinds, modes,
bytes; no temp file left), and running it again succeeds.
"""

from __future__ import annotations

import errno
import os
import shutil
import stat
from collections.abc import Callable
from pathlib import Path

import pytest

from fleetctl.deploy import files
from fleetctl.deploy import operations as ops
from fleetctl.deploy.export import export_robot
from fleetctl.deploy.files import WriteFailed
from fleetctl.errors import ExitCode
from tests.deploy.conftest import SeededKeySource, make_fleet
from tests.deploy.test_bundle import fake_wheel

Snapshot = dict[str, tuple[str, int, bytes]]


def snapshot(root: Path) -> Snapshot:
    """Every path under *root*: its kind, mode and bytes (a symlink's target)."""
    out: Snapshot = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            st = path.lstat()
            if stat.S_ISLNK(st.st_mode):
                out[str(path.relative_to(root))] = ("link", 0, os.readlink(path).encode())
            elif stat.S_ISDIR(st.st_mode):
                out[str(path.relative_to(root))] = ("dir", stat.S_IMODE(st.st_mode), b"")
            else:
                out[str(path.relative_to(root))] = ("file", stat.S_IMODE(st.st_mode),
                                                    path.read_bytes())
    return out


def _add_by_hand(fleet_dir: Path) -> None:
    path = fleet_dir / "fleet.yaml"
    path.write_text(path.read_text().replace(
        "users:\n", "- name: hand1\n  ip: 10.8.0.30\nusers:\n", 1))


Operation = Callable[[Path, Path], object]

OPERATIONS: dict[str, Operation] = {
    "add-robot": lambda d, out: ops.add_robot(d, "r3", keys=SeededKeySource("r3")),
    "remove-robot": lambda d, out: ops.remove_robot(d, "husky1"),
    "add-user": lambda d, out: ops.add_user(d, "new@example.com", "viewer"),
    "remove-user": lambda d, out: ops.remove_user(d, "viewer@example.com"),
    "set-user": lambda d, out: ops.set_user_robots(d, "viewer@example.com", ["husky1"]),
    "set-endpoint": lambda d, out: ops.set_endpoint(d, "other.example.org:51820"),
    "render": lambda d, out: ops.render_fleet(d, force=True),
    "init --force": lambda d, out: ops.create_fleet(d, name="again", force=True,
                                                    keys=SeededKeySource("again")),
    "export": lambda d, out: export_robot(d, "husky1", out / "bundle",
                                          wheel=fake_wheel(out.parent.parent)),
    "export tarball": lambda d, out: export_robot(d, "husky1", out / "b.tgz",
                                                  wheel=fake_wheel(out.parent.parent)),
}


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    fleet_dir = make_fleet(tmp_path_factory.mktemp("base"))
    _add_by_hand(fleet_dir)  # render gives it keys and files
    return fleet_dir


def _fresh(base: Path, tmp_path: Path, i: int) -> tuple[Path, Path]:
    work = tmp_path / f"run{i}"
    shutil.copytree(base, work / "fleet", symlinks=True)
    (work / "out").mkdir()
    return work / "fleet", work / "out"


class Injected:
    """Counts calls of a primitive; makes call number *fail_at* raise ENOSPC."""

    def __init__(self, real: Callable[..., None], fail_at: int | None) -> None:
        self.real, self.fail_at, self.calls = real, fail_at, 0

    def __call__(self, *args: object) -> None:
        self.calls += 1
        if self.calls == self.fail_at:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(args[-1]))
        self.real(*args)


@pytest.mark.parametrize("primitive", ["write_all", "rename"])
@pytest.mark.parametrize("name", list(OPERATIONS))
def test_a_failure_at_any_write_changes_nothing(base: Path, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch,
                                                name: str, primitive: str) -> None:
    operation, real = OPERATIONS[name], getattr(files, primitive)
    counter = Injected(real, None)
    fleet_dir, out = _fresh(base, tmp_path, 0)
    monkeypatch.setattr(files, primitive, counter)
    operation(fleet_dir, out)
    assert counter.calls > 0
    for n in range(1, counter.calls + 1):
        fleet_dir, out = _fresh(base, tmp_path, n)
        before = snapshot(fleet_dir.parent)
        monkeypatch.setattr(files, primitive, Injected(real, n))
        with pytest.raises(WriteFailed) as info:
            operation(fleet_dir, out)
        assert "No space left on device" in str(info.value) and "\n" not in str(info.value)
        assert info.value.exit_code is ExitCode.ENVIRONMENT
        assert snapshot(fleet_dir.parent) == before, f"{name}: write {n} failed"
        monkeypatch.setattr(files, primitive, real)
        operation(fleet_dir, out)  # the retry works


def test_add_robot_retry_after_disk_full_has_its_keys(base: Path, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """The issue's case: the first key file written, then the disk full."""
    fleet_dir, _ = _fresh(base, tmp_path, 0)
    monkeypatch.setattr(files, "write_all", Injected(files.write_all, 2))
    with pytest.raises(WriteFailed):
        ops.add_robot(fleet_dir, "r3")
    assert not (fleet_dir / "keys/robots/r3.key").exists()
    monkeypatch.undo()
    result = ops.add_robot(fleet_dir, "r3")
    assert result.public_key and (fleet_dir / "keys/robots/r3.psk").is_file()
    assert "r3" in (fleet_dir / "server/wireguard/wg0.conf").read_text()
