"""``fleetctl export``: refusals, and the fleetctl wheel it ships."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from fleetctl.deploy.export import export_robot
from fleetctl.errors import ConfigError, ExitCode, FleetError
from tests.deploy.test_bundle import fake_wheel


def test_export_refuses_without_an_endpoint(fleet_dir: Path, tmp_path: Path) -> None:
    path = fleet_dir / "fleet.yaml"
    doc = yaml.safe_load(path.read_text())
    del doc["endpoint"]
    path.write_text(yaml.safe_dump(doc, sort_keys=False))

    def never(dest: Path) -> Path:
        raise AssertionError("no wheel is built for a bundle that cannot work")

    with pytest.raises(ConfigError) as info:
        export_robot(fleet_dir, "husky1", tmp_path / "b", build_wheel=never)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message and "endpoint" in message
    assert "fleetctl set-endpoint HOST:PORT" in message
    assert info.value.exit_code is ExitCode.CONFIG
    assert not (tmp_path / "b").exists()


def test_export_builds_the_wheel_when_none_is_given(fleet_dir: Path, tmp_path: Path) -> None:
    built: list[Path] = []

    def build(dest: Path) -> Path:
        built.append(dest)
        return fake_wheel(dest)

    out = export_robot(fleet_dir, "husky1", tmp_path / "b", build_wheel=build).path
    assert len(built) == 1 and not built[0].exists()  # a temporary directory, removed
    assert (out / "fleetctl-0.1.0-py3-none-any.whl").is_file()


def test_export_dry_run_writes_nothing(fleet_dir: Path, tmp_path: Path) -> None:
    result = export_robot(fleet_dir, "husky1", tmp_path / "b", dry_run=True,
                          wheel=fake_wheel(tmp_path))
    assert result.outcome.dry_run and len(result.outcome.changes) == 8
    assert not (tmp_path / "b").exists()


@pytest.mark.slow
def test_export_ships_a_wheel_of_this_fleetctl(fleet_dir: Path, tmp_path: Path) -> None:
    import zipfile

    out = export_robot(fleet_dir, "husky1", tmp_path / "b").path
    wheel = out / "fleetctl-0.1.0-py3-none-any.whl"
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
    assert "fleetctl/client/transport.py" in names
    assert "fleetctl/deploy/bundle.py" in names


# --- issue 14: temp files, the --out directory, --out errors ----------------------------


def test_export_never_follows_a_planted_temp_name(fleet_dir: Path, tmp_path: Path) -> None:
    import os

    out = tmp_path / "b"
    out.mkdir()
    victim = tmp_path / "victim"
    victim.write_text("keep\n")
    # The name the old code used, and a guess at every pid nearby: temp names are random.
    for pid in range(os.getpid() - 5, os.getpid() + 5):
        (out / f".wg0.conf.{pid}.tmp").symlink_to(victim)
    export_robot(fleet_dir, "husky1", out, wheel=fake_wheel(tmp_path))
    assert victim.read_text() == "keep\n"
    assert (out / "wg0.conf").read_text().count("PrivateKey") == 1
    assert not (out / "wg0.conf").is_symlink()


def test_export_keeps_an_existing_directory_mode(fleet_dir: Path, tmp_path: Path) -> None:
    import stat

    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)
    export_robot(fleet_dir, "husky1", shared, wheel=fake_wheel(tmp_path))
    assert stat.S_IMODE(shared.stat().st_mode) == 0o1777
    assert stat.S_IMODE((shared / "wg0.conf").stat().st_mode) == 0o600
    new = export_robot(fleet_dir, "husky1", tmp_path / "new", wheel=fake_wheel(tmp_path)).path
    assert stat.S_IMODE(new.stat().st_mode) == 0o700


@pytest.mark.parametrize("suffix", [".tar.gz", ".tgz", ".TGZ", ".Tar.Gz"])
def test_export_tarball_suffixes(fleet_dir: Path, tmp_path: Path, suffix: str) -> None:
    """Any case: `husky1.TGZ` was a directory of that name."""
    import tarfile

    out = export_robot(fleet_dir, "husky1", tmp_path / f"husky1{suffix}",
                       wheel=fake_wheel(tmp_path)).path
    assert out.is_file()
    with tarfile.open(out) as tar:
        assert "husky1/wg0.conf" in tar.getnames()


@pytest.mark.parametrize("name", ["husky1.zip", "husky1.tar", "husky1.tar.xz", "b.tar.bz2",
                                  "b.ZIP", "b.tar.zst", "b.gz"])
def test_export_refuses_an_archive_it_does_not_write(
        fleet_dir: Path, tmp_path: Path, name: str) -> None:
    """`--out husky1.zip` made a directory called husky1.zip holding the private key."""
    with pytest.raises(FleetError, match=rf"^--out .*{name}: export writes a directory or a "
                       r"\.tar\.gz / \.tgz tarball, not a \.") as info:
        export_robot(fleet_dir, "husky1", tmp_path / name, wheel=fake_wheel(tmp_path))
    assert info.value.exit_code is ExitCode.USAGE
    assert not (tmp_path / name).exists()
    # An existing directory of that name is a directory the caller chose.
    (tmp_path / name).mkdir()
    export_robot(fleet_dir, "husky1", tmp_path / name, wheel=fake_wheel(tmp_path))
    assert (tmp_path / name / "wg0.conf").is_file()


def test_export_out_errors_change_nothing(fleet_dir: Path, tmp_path: Path) -> None:
    from fleetctl.errors import ConfigError, ConflictError

    wheel = fake_wheel(tmp_path)
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    with pytest.raises(ConflictError, match=r"^--out .*afile: exists and is not a directory"):
        export_robot(fleet_dir, "husky1", afile, wheel=wheel)
    assert afile.read_text() == "mine\n"
    adir = tmp_path / "adir.tgz"
    adir.mkdir()
    with pytest.raises(ConflictError, match="is not a regular file"):
        export_robot(fleet_dir, "husky1", adir, wheel=wheel)
    with pytest.raises(FleetError) as info:
        export_robot(fleet_dir, "husky1", Path("/proc/fleetctl-nope.tgz"), wheel=wheel)
    assert str(info.value).startswith("--out /proc/fleetctl-nope.tgz: ")
    assert info.value.exit_code is ExitCode.ENVIRONMENT and "\n" not in str(info.value)
    for missing in (tmp_path / "no" / "such" / "b.tgz", tmp_path / "nodir" / "bundle"):
        with pytest.raises(ConfigError, match=rf"^--out {missing}: directory {missing.parent} "
                                              "does not exist$"):
            export_robot(fleet_dir, "husky1", missing, wheel=wheel)
    assert not (tmp_path / "no").exists() and not (tmp_path / "nodir").exists()


def test_export_replaces_only_what_an_earlier_export_wrote(fleet_dir: Path,
                                                           tmp_path: Path) -> None:
    """`--out .` (or `--out ~/robots`, or an `--out "$DIR"` left empty: the current
    directory) replaced the operator's own README.md and compose.yaml there."""
    from fleetctl.errors import ConflictError

    wheel = fake_wheel(tmp_path)
    project = tmp_path / "project"
    project.mkdir()
    (project / "README.md").write_text("# my robots\n")
    (project / "notes.txt").write_text("keep\n")
    with pytest.raises(ConflictError, match=rf"^--out {project}: {project}/README.md exists and "
                       r"is not a file of an earlier export \(edited, or not fleetctl's\)") as info:
        export_robot(fleet_dir, "husky1", project, wheel=wheel)
    assert info.value.exit_code is ExitCode.CONFLICT
    assert sorted(p.name for p in project.iterdir()) == ["README.md", "notes.txt"]
    assert (project / "README.md").read_text() == "# my robots\n"
    # An earlier bundle is brought up to date, every file of it (compose.yaml included).
    bundle = export_robot(fleet_dir, "husky1", tmp_path / "b", wheel=wheel).path
    (fleet_dir / "fleet.yaml").write_text(
        (fleet_dir / "fleet.yaml").read_text().replace("ros_domain_id: 0", "ros_domain_id: 5"))
    # compose.yaml of a bundle exported before it carried a digest line: as written then.
    compose_file = bundle / "compose.yaml"
    compose_file.write_text(compose_file.read_text().split("\n", 1)[1])
    export_robot(fleet_dir, "husky1", bundle, wheel=wheel)
    assert "ROS_DOMAIN_ID=5" in (bundle / "fleetctl.env").read_text()
    # ... but not a file of it edited by hand since.
    client = bundle / "client.yaml"
    client.write_text(client.read_text() + "# tuned on site\n")
    with pytest.raises(ConflictError, match=r"client.yaml exists and is not a file of an "):
        export_robot(fleet_dir, "husky1", bundle, wheel=wheel)
    assert client.read_text().endswith("# tuned on site\n")


def test_export_of_a_robot_whose_keys_were_lost_says_restore_them(fleet_dir: Path,
                                                                   tmp_path: Path) -> None:
    """It said `has no keys yet (run 'fleetctl render' first)`, and render then refused:
    new keys would cut off the robot that uses the old ones."""
    for suffix in (".key", ".psk"):
        (fleet_dir / "keys" / "robots" / f"husky1{suffix}").unlink()
    with pytest.raises(ConfigError, match=r"husky1.key and husky1.psk: not found, but "
                       r".*robots/husky1/wireguard/wg0.conf was made from them .*restore them "
                       r"from a backup"):
        export_robot(fleet_dir, "husky1", tmp_path / "b", wheel=fake_wheel(tmp_path))
    assert not (tmp_path / "b").exists()
