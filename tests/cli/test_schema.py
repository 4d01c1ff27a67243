"""``fleetctl schema``: export, describe, types, and their errors."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from fleetctl.cli.main import main
from fleetctl.errors import ExitCode

FLATC = shutil.which("flatc") or str(Path(sys.executable).with_name("flatc"))


def test_export_chosen_types_compiles_with_flatc(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "fbs"
    code = main(["schema", "export", str(out), "--type", "sensor_msgs/LaserScan",
                 "-t", "RobofleetStatus", "--output", "json"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    files = sorted(Path(p).relative_to(out).as_posix() for p in result["files"])
    assert files == ["MsgMetadata.fbs", "amrl_msgs/msg/RobofleetStatus.fbs",
                     "builtin_interfaces/msg/Time.fbs", "sensor_msgs/msg/LaserScan.fbs",
                     "std_msgs/msg/Header.fbs"]
    proc = subprocess.run([FLATC, "--python", "-o", str(tmp_path / "py"), "-I", str(out),
                           *result["files"]], capture_output=True, text=True, timeout=60,
                          check=False)
    assert proc.returncode == 0, proc.stderr


def test_export_all_by_default(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["schema", "export", str(tmp_path)]) == 0
    assert "wrote 171 .fbs files" in capsys.readouterr().out
    assert (tmp_path / "tf2_msgs/msg/TFMessage.fbs").is_file()


def test_unknown_type_is_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["schema", "export", str(tmp_path), "--type", "nope_msgs/Nothing"]) == (
        ExitCode.USAGE)
    err = capsys.readouterr().err
    assert "unknown message type nope_msgs/msg/Nothing" in err and "Traceback" not in err
    assert main(["schema", "export", str(tmp_path), "--type", "not a type"]) == ExitCode.USAGE
    assert "bad message type name" in capsys.readouterr().err


def test_unwritable_directory_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["schema", "export", str(blocker / "sub")]) == ExitCode.ENVIRONMENT
    assert f"{blocker / 'sub'}: cannot write schemas" in capsys.readouterr().err


def test_a_file_where_the_directory_goes_is_a_conflict(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """As `export --out FILE` (exit 4); it used to be exit 1."""
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    assert main(["schema", "export", str(afile)]) == ExitCode.CONFLICT
    assert capsys.readouterr().err == (f"fleetctl: error: {afile}: exists and is not a "
                                       "directory (give a new or existing directory to write "
                                       "the .fbs files into)\n")
    assert afile.read_text() == "mine\n"


def test_describe_prints_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["schema", "describe", "geometry_msgs/PoseStamped"]) == 0
    layout = json.loads(capsys.readouterr().out)
    assert layout["root"] == "geometry_msgs/msg/PoseStamped"
    assert main(["schema", "describe", "x/Y"]) == ExitCode.USAGE


def test_types_lists_the_registry(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["schema", "types", "-o", "json"]) == 0
    names = json.loads(capsys.readouterr().out)
    assert "amrl_msgs/msg/RobofleetSubscription" in names


@pytest.mark.ros
def test_types_from_the_installed_ros_packages(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["schema", "types", "--from-ros", "-o", "json"]) == 0
    # nav_msgs/msg/Goals ships in the Jazzy wheels (and fleetctl), not in the rosbags store.
    assert "nav_msgs/msg/Goals" in json.loads(capsys.readouterr().out)
