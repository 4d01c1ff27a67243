"""``fleetctl export``: refusals, and the fleetctl wheel it ships."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from fleetctl.deploy.export import export_robot
from fleetctl.errors import ConfigError, ExitCode
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
