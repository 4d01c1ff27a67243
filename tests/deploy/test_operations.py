"""fleetctl.deploy.operations: inputs an operator can get wrong, reported as one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from fleetctl.deploy import operations as ops
from fleetctl.errors import ConfigError


@pytest.mark.parametrize("sub", ["afile", "afile/fleet"])
def test_init_on_a_file_is_a_config_error(tmp_path: Path, sub: str) -> None:
    (tmp_path / "afile").write_text("not a directory\n")
    with pytest.raises(ConfigError, match="afile exists and is not a directory"):
        ops.create_fleet(tmp_path / sub)
    assert (tmp_path / "afile").read_text() == "not a directory\n"


def test_init_in_a_new_nested_directory_still_works(tmp_path: Path) -> None:
    ops.create_fleet(tmp_path / "a" / "b", dry_run=True)


def test_a_deployed_robot_whose_keys_are_gone_gets_no_new_ones_silently(
        tmp_path: Path) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    ops.add_robot(fleet_dir, "r1")
    (fleet_dir / "keys/robots/r1.key").unlink()
    (fleet_dir / "keys/robots/r1.psk").unlink()
    conf = fleet_dir / "robots/r1/wireguard/wg0.conf"
    before = conf.read_text()
    # New keys would cut off the robot running the bundle exported from this config.
    for operation in (lambda: ops.render_fleet(fleet_dir),
                      lambda: ops.add_user(fleet_dir, "a@example.com", "viewer")):
        with pytest.raises(ConfigError, match=r"r1\.key and r1\.psk: not found, but .*"
                                              r"wg0\.conf was made from them"):
            operation()
    assert conf.read_text() == before
    assert not (fleet_dir / "keys/robots/r1.key").exists()
    # The way out the message gives: the config goes, render makes new keys.
    conf.unlink()
    ops.render_fleet(fleet_dir)
    assert (fleet_dir / "keys/robots/r1.key").is_file() and conf.is_file()


def test_a_robot_added_to_fleet_yaml_by_hand_still_gets_its_keys(tmp_path: Path) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    fleet_yaml = fleet_dir / "fleet.yaml"
    fleet_yaml.write_text(fleet_yaml.read_text().replace(
        "robots: []", "robots:\n  - name: r2\n    ip: 10.8.0.7"))
    ops.render_fleet(fleet_dir)
    assert (fleet_dir / "keys/robots/r2.key").is_file()


def test_a_key_others_may_read_is_refused_as_ssh_refuses_one(tmp_path: Path) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    ops.add_robot(fleet_dir, "r1")
    key = fleet_dir / "keys/robots/r1.key"
    outside = tmp_path / "r1.key"  # a copy kept elsewhere, world-readable, linked in
    outside.write_text(key.read_text())
    outside.chmod(0o644)
    key.unlink()
    key.symlink_to(outside)
    with pytest.raises(ConfigError, match=r"r1\.key: key file is readable or writable by "
                                          r"others \(mode 0644, through a symbolic link\)"):
        ops.render_fleet(fleet_dir)
    outside.chmod(0o600)
    ops.render_fleet(fleet_dir)  # the operator's call: a private key, wherever it lives


def test_a_linked_fleet_yaml_is_read_but_never_replaced_by_a_copy(tmp_path: Path) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    repo = tmp_path / "repo.yaml"  # the operator's file, kept in a repository
    (fleet_dir / "fleet.yaml").rename(repo)
    (fleet_dir / "fleet.yaml").symlink_to(repo)
    before = repo.read_text()
    ops.render_fleet(fleet_dir)  # nothing to change in fleet.yaml: fine through the link
    with pytest.raises(ConfigError, match=r"fleet\.yaml is a symbolic link \(to .*repo\.yaml\)"
                                          r": fleetctl replaces fleet\.yaml whole"):
        ops.add_robot(fleet_dir, "r1")
    assert (fleet_dir / "fleet.yaml").is_symlink() and repo.read_text() == before
