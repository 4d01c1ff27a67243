"""fleetctl.deploy.files: planning writes where a parent directory is a regular file."""

from __future__ import annotations

import errno
import re
import shutil
from pathlib import Path

import pytest

from fleetctl.deploy import files
from fleetctl.deploy import operations as ops
from fleetctl.errors import ConfigError, FleetError


def test_a_file_where_a_directory_belongs_is_one_error_and_changes_nothing(
        tmp_path: Path) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    ops.add_robot(fleet_dir, "r1")
    # A directory the fleet's check does not name (fleet.directory_problems): the write
    # itself says which path is in the way.
    inner = fleet_dir / "robots" / "r1" / "wireguard"
    shutil.rmtree(inner)
    inner.write_text("in the way\n")
    assert ops.render_fleet(fleet_dir, dry_run=True).changes  # a preview, no traceback
    with pytest.raises(FleetError, match=r"robots/r1/wireguard/\S+: cannot write: Not a "
                                         r"directory; nothing was changed"):
        ops.render_fleet(fleet_dir)
    assert inner.read_text() == "in the way\n"
    # One the check names: refused before any write, the dry run too, naming it.
    server = fleet_dir / "server"
    shutil.rmtree(server)
    server.write_text("in the way\n")
    for dry_run in (True, False):
        with pytest.raises(ConfigError, match=rf"^{re.escape(str(server))}: not a directory "
                                              r"but a file \(it holds the server's"):
            ops.render_fleet(fleet_dir, dry_run=dry_run)
    assert server.read_text() == "in the way\n"


def test_a_write_that_fails_names_the_file_not_its_temp(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    before = (fleet_dir / "fleet.yaml").read_bytes()

    def refused(prefix: str, suffix: str, dir: Path) -> tuple[int, str]:
        # What a directory the operator may not write gives: the temp file's own name.
        raise PermissionError(errno.EACCES, "Permission denied",
                              str(Path(dir) / f"{prefix}17vn9af5{suffix}"))

    monkeypatch.setattr(files.tempfile, "mkstemp", refused)
    with pytest.raises(FleetError) as info:
        ops.set_endpoint(fleet_dir, "vpn.example.org:51820")
    named, _, rest = str(info.value).partition(": ")
    assert rest == "cannot write: Permission denied; nothing was changed"
    # The first file the command writes (the certificate, whose names follow the
    # endpoint), as the operator knows it.
    assert Path(named) == fleet_dir / "server/tls/cert.pem"
    assert (fleet_dir / "fleet.yaml").read_bytes() == before


def _tree(root: Path) -> dict[str, bytes | str]:
    """Every path below *root*: a file's bytes, a link's target, a directory's mode."""
    out: dict[str, bytes | str] = {}
    for p in sorted(root.rglob("*")):
        key = str(p.relative_to(root))
        if p.is_symlink():
            out[key] = f"-> {p.readlink()}"
        elif p.is_dir():
            out[key] = oct(p.stat().st_mode)
        else:
            out[key] = p.read_bytes()
    return out


_CHANGES = {
    "set-endpoint": lambda f: ops.set_endpoint(f, "vpn2.example.org:51820"),
    "add-robot": lambda f: ops.add_robot(f, "jackal2"),
    "render --dry-run": lambda f: ops.render_fleet(f, dry_run=True),
    "remove-robot": lambda f: ops.remove_robot(f, "husky1"),
}


@pytest.mark.parametrize(("linked", "change"), [
    ("robots/husky1/wireguard", "set-endpoint"), ("robots/husky1/wireguard", "render --dry-run"),
    ("robots/husky1", "set-endpoint"), ("robots", "remove-robot"), ("robots", "add-robot"),
    ("keys/robots", "add-robot"), ("keys/robots", "remove-robot"), ("keys", "set-endpoint"),
    ("server/wireguard", "add-robot"), ("server", "render --dry-run")])
def test_a_directory_that_is_a_link_is_never_written_through(
        tmp_path: Path, linked: str, change: str) -> None:
    """A link at robots/NAME/wireguard had set-endpoint write the robot's private key into
    the directory it points to (and force 0700 on it)."""
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir, endpoint="vpn.example.org:51820")
    ops.add_robot(fleet_dir, "husky1")
    elsewhere = tmp_path / "elsewhere"
    shutil.move(fleet_dir / linked, elsewhere)
    elsewhere.chmod(0o755)
    (fleet_dir / linked).symlink_to(elsewhere)
    before, outside = _tree(fleet_dir), _tree(elsewhere)
    with pytest.raises(ConfigError) as info:
        _CHANGES[change](fleet_dir)
    assert str(info.value).startswith(
        f"{fleet_dir / linked} is a symbolic link (to {elsewhere}), which fleetctl never "
        "writes through: make it a directory of its own")
    assert info.value.exit_code == 3
    assert _tree(fleet_dir) == before and _tree(elsewhere) == outside
    assert oct(elsewhere.stat().st_mode) == oct(0o40755)


def test_a_fleet_directory_reached_through_a_link_is_fine(tmp_path: Path) -> None:
    real = tmp_path / "real"
    ops.create_fleet(real, endpoint="vpn.example.org:51820")
    (tmp_path / "link").symlink_to(real)
    ops.add_robot(tmp_path / "link", "husky1")
    assert (real / "robots/husky1/wireguard/wg0.conf").is_file()


@pytest.mark.parametrize("directory", ["keys", "keys/robots"])
def test_key_directories_are_0700_again_after_any_change(tmp_path: Path,
                                                         directory: str) -> None:
    """docs/operator.md: fleetctl forces 0700 on keys/; a keys/ opened to 0755 stayed so
    through render and add-user (only writing a key into it forced the mode)."""
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir, endpoint="vpn.example.org:51820")
    ops.add_robot(fleet_dir, "husky1")
    for change in (lambda: ops.render_fleet(fleet_dir),
                   lambda: ops.add_user(fleet_dir, "bob@example.org", "viewer")):
        (fleet_dir / directory).chmod(0o755)
        ops.render_fleet(fleet_dir, dry_run=True)
        assert (fleet_dir / directory).stat().st_mode & 0o777 == 0o755  # a preview
        change()
        assert (fleet_dir / directory).stat().st_mode & 0o777 == 0o700


def test_a_missing_server_key_says_how_to_recover(tmp_path: Path) -> None:
    """It said `keys/server.key: key file not found` and no more: the one key that must
    never be made again in place (every robot's config names it)."""
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir, endpoint="vpn.example.org:51820")
    ops.add_robot(fleet_dir, "husky1")
    (fleet_dir / "keys" / "server.key").unlink()
    before = _tree(fleet_dir)
    for change in (lambda: ops.render_fleet(fleet_dir), lambda: ops.add_robot(fleet_dir, "j2")):
        with pytest.raises(ConfigError) as info:
            change()
        assert str(info.value) == (
            f"{fleet_dir}/keys/server.key: key file not found: restore it from a backup of "
            "the fleet directory (a new server key would cut off every robot already "
            "deployed; `fleetctl init --force` makes a new fleet)")
    assert _tree(fleet_dir) == before


def test_a_write_under_a_deleted_directory_is_a_creation(tmp_path: Path) -> None:
    """A file the plan deletes (with its directory) and writes again with the same bytes
    was judged `unchanged` against the old one: never written, and the deletion took it
    (`init --force` lost server/server.yaml). Preview and apply agree that it is created."""
    root = tmp_path / "f"
    (root / "server").mkdir(parents=True)
    (root / "server" / "server.yaml").write_bytes(b"same\n")
    (root / "server" / "server.yaml").chmod(0o644)
    (root / "server" / "old.yaml").write_bytes(b"old\n")

    def plan() -> files.Plan:
        p = files.Plan(root=root)
        p.delete(root / "server")
        p.write(root / "server" / "server.yaml", b"same\n")
        return p

    expected = [files.Change(root / "server", files.ChangeKind.DELETE),
                files.Change(root / "server" / "server.yaml", files.ChangeKind.CREATE)]
    assert plan().preview() == expected
    assert plan().apply() == expected
    assert sorted(p.name for p in (root / "server").iterdir()) == ["server.yaml"]
    assert (root / "server" / "server.yaml").read_bytes() == b"same\n"
