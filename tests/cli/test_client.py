"""``fleetctl client``: bad configs are reported with file and field, never a traceback."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

from fleetctl.cli.main import main
from fleetctl.errors import ConfigError, ExitCode


def test_invalid_config_names_file_entry_and_field(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "client.yaml"
    config.write_text("server_url: ws://127.0.0.1:1/\nrobot_name: r\n"
                      "publish:\n  - {topic: scan, type: sensor_msgs/msg/LaserScan}\n")
    assert main(["client", "--config", str(config)]) == ExitCode.CONFIG
    err = capsys.readouterr().err
    assert f"{config}: publish[0] (scan): topic" in err
    assert "Traceback" not in err


def test_missing_config_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope.yaml"
    assert main(["client", "--config", str(missing)]) == ExitCode.CONFIG
    assert str(missing) in capsys.readouterr().err


@pytest.mark.ros
def test_uninstalled_message_type_is_a_config_error(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str],
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("rclpy")
    monkeypatch.setenv("ROS_DOMAIN_ID", "38")
    config = tmp_path / "client.yaml"
    # diagnostic_msgs is in the wire registry (rosbags) but has no rclpy package here
    # (tf2_msgs was the example until scripts/ros_msgs.sh built it).
    pytest.importorskip("rclpy")
    if importlib.util.find_spec("diagnostic_msgs") is not None:
        pytest.skip("diagnostic_msgs is installed")
    config.write_text("server_url: ws://127.0.0.1:1/\nrobot_name: r\n"
                      "publish:\n  - {topic: /diag, type: diagnostic_msgs/msg/DiagnosticArray}\n")
    assert main(["client", "--config", str(config)]) == ExitCode.CONFIG
    err = capsys.readouterr().err
    assert "publish[0] (/diag): type:" in err and "diagnostic_msgs" in err


def test_unknown_log_level_is_a_usage_error(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "client.yaml"
    config.write_text("server_url: ws://127.0.0.1:1/\nrobot_name: r\n")
    assert main(["client", "--config", str(config), "--log-level", "LOUD"]) == ExitCode.USAGE
    err = capsys.readouterr().err
    assert "--log-level: unknown level 'LOUD'; use one of DEBUG, INFO, WARNING, ERROR" in err
    assert "Traceback" not in err


def test_the_stop_line_says_what_the_server_acknowledged() -> None:
    # "133 sent" was printed for a client that never reached its server.
    from fleetctl.cli.client import stop_line

    never = {"bridge": {"local_in": 133, "sent": 133, "rate_limited": 0, "published_local": 0},
             "topics": {"/r/chatter": {"acked": 0, "sent_frames": 0}}, "connects": 0,
             "reconnects": 0, "no_drop_overflow": 113}
    assert stop_line(never) == (
        "client stopped: 133 local messages in, 133 handed to the link, 0 acknowledged by the "
        "server (status included), 0 rate limited, 0 frames published locally, 0 connections "
        "(0 reconnects), "
        "113 no_drop overflow")
    reached = {**never, "topics": {"/r/a": {"acked": 100}, "/r/b": {"acked": 20}},
               "connects": 2, "reconnects": 1}
    assert "120 acknowledged by the server" in stop_line(reached)
    assert "2 connections (1 reconnects)" in stop_line(reached)
    # What DDS lost before the client took it (publisher sequence gaps) is said when any.
    assert "lost before" not in stop_line(reached)
    # So are no_drop messages republished past the local writer's history (the last hop).
    assert "past the local history" not in stop_line(reached)
    risky = {**reached, "bridge": {**never["bridge"], "no_drop_at_risk": 5}}
    assert stop_line(risky).endswith(
        ", 5 no_drop messages republished in bursts past the local history (a slow local "
        "reader may have missed them)")
    lossy = {**reached, "bridge": {**never["bridge"], "lost_before_client": 17}}
    assert stop_line(lossy).endswith(
        "113 no_drop overflow, 17 local messages lost before the client took them")


@pytest.mark.parametrize("value", ["300", "abc", "-1", "1.5"])
def test_a_bad_ros_domain_id_is_one_line(value: str, tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    # 300: exit 1 with only Fast DDS's "port number is too high"; abc: an rclpy traceback.
    monkeypatch.setenv("ROS_DOMAIN_ID", value)
    config = tmp_path / "client.yaml"
    config.write_text("server_url: ws://127.0.0.1:1/\nrobot_name: r\n")
    assert main(["client", "--config", str(config)]) == ExitCode.CONFIG
    err = capsys.readouterr().err
    assert f"ROS_DOMAIN_ID={value!r} (environment): must be an integer from 0 to 232" in err
    assert "Traceback" not in err


def _client_process(config: Path, **env: str) -> subprocess.CompletedProcess[str]:
    """`fleetctl client` as a robot's service runs it: its own process and environment."""
    clean = {k: v for k, v in os.environ.items()
             if k not in ("RMW_IMPLEMENTATION", "ROS_DOMAIN_ID", "AMENT_PREFIX_PATH")}
    return subprocess.run([sys.executable, "-m", "fleetctl.cli.main", "client", "--config",
                           str(config)], env={**clean, **env}, capture_output=True,
                          text=True, timeout=120, check=False)


@pytest.mark.ros
def test_an_rmw_that_is_not_installed_is_one_line_naming_the_installed_ones(
        tmp_path: Path) -> None:
    """An operator's pass: RMW_IMPLEMENTATION naming an RMW that is not installed made
    the client exit 102 from rcl at rclpy's import, with rcl's own text ("Expected RMW
    implementation identifier of ... but instead found ...", a C source path). Now it is
    a config error (exit 3, as a bad ROS_DOMAIN_ID) naming the variable, its value and
    what is installed, found as rmw_implementation finds them (the ament index)."""
    pytest.importorskip("rclpy")  # the ros extra: an RMW registered in the ament index
    # Another prefix on AMENT_PREFIX_PATH (apt's ROS, an overlay) registers one more.
    overlay = tmp_path / "overlay"
    (overlay / "share/ament_index/resource_index/rmw_typesupport").mkdir(parents=True)
    (overlay / "share/ament_index/resource_index/rmw_typesupport/rmw_overlay_cpp").touch()
    config = tmp_path / "client.yaml"
    config.write_text("server_url: ws://127.0.0.1:1/\nrobot_name: r\n")
    done = _client_process(config, RMW_IMPLEMENTATION="rmw_cyclonedds_nope_cpp",
                           AMENT_PREFIX_PATH=str(overlay), ROS_DISTRO="jazzy")
    assert done.returncode == ExitCode.CONFIG, done.stderr
    from fleetctl.cli.client import installed_rmw_implementations

    installed = installed_rmw_implementations({})
    assert "rmw_fastrtps_cpp" in installed  # the ros extra's
    listed = ", ".join(sorted([*installed, "rmw_overlay_cpp"]))
    assert done.stderr == (
        "fleetctl: error: RMW_IMPLEMENTATION='rmw_cyclonedds_nope_cpp' (environment): not "
        f"installed here; installed: {listed}. Install it (apt: "
        "ros-jazzy-rmw-cyclonedds-nope-cpp) or choose an installed one (fleetctl.env; "
        "robots[].rmw_implementation in fleet.yaml, then `fleetctl export`)\n")
    assert done.stdout == ""
    # A value no RMW could have: quoted, on the same one line, no package to suggest.
    done = _client_process(config, RMW_IMPLEMENTATION="rmw\nfoo")
    assert done.returncode == ExitCode.CONFIG and len(done.stderr.splitlines()) == 1
    assert done.stderr.startswith("fleetctl: error: RMW_IMPLEMENTATION='rmw\\nfoo' "
                                  "(environment): not installed here; installed: ")


def test_the_installed_rmws_come_from_every_ament_prefix(tmp_path: Path) -> None:
    from fleetctl.cli.client import _check_rmw_implementation, installed_rmw_implementations

    def prefix(name: str, *rmws: str) -> Path:
        index = tmp_path / name / "share/ament_index/resource_index/rmw_typesupport"
        index.mkdir(parents=True)
        for rmw in rmws:
            (index / rmw).touch()
        return tmp_path / name

    apt = prefix("opt", "rmw_fastrtps_cpp", "rmw_cyclonedds_cpp", "rmw_implementation")
    venv = prefix("venv", "rmw_fastrtps_cpp", "rmw_zenoh_cpp")
    env = {"AMENT_PREFIX_PATH": f"{apt}{os.pathsep}{tmp_path / 'gone'}"}
    assert installed_rmw_implementations(env, str(venv)) == [
        "rmw_cyclonedds_cpp", "rmw_fastrtps_cpp", "rmw_zenoh_cpp"]
    assert installed_rmw_implementations({}, str(tmp_path / "bare")) == []
    _check_rmw_implementation({"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp", **env})
    _check_rmw_implementation({"RMW_IMPLEMENTATION": "", **env})  # rcl's default
    with pytest.raises(ConfigError, match=r"RMW_IMPLEMENTATION='rmw_connextdds' "
                       r"\(environment\): not installed here; installed: rmw_cyclonedds_cpp"):
        _check_rmw_implementation({"RMW_IMPLEMENTATION": "rmw_connextdds",
                                   "AMENT_PREFIX_PATH": str(apt)})


@pytest.mark.parametrize(("mode", "warned"), [(0o644, True), (0o640, True), (0o600, False)])
def test_a_token_file_others_may_read_is_warned_of(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
        mode: int, warned: bool) -> None:
    """`echo TOKEN > robot.token` under the usual umask is 0644: the client took it without
    a word (--token-file of the other commands warns). The domain check then stops the
    client before ROS, so no rclpy is needed."""
    monkeypatch.setenv("ROS_DOMAIN_ID", "300")
    token = tmp_path / "robot.token"
    token.write_text("s3cret-token\n")
    token.chmod(mode)
    config = tmp_path / "client.yaml"
    config.write_text("server_url: ws://127.0.0.1:1/\nrobot_name: r\ntoken_file: robot.token\n")
    assert main(["client", "--config", str(config)]) == ExitCode.CONFIG
    said = [r.getMessage() for r in caplog.records if "other users may read" in r.getMessage()]
    expected = [f"token_file {token}: other users may read it (mode {mode:04o}): chmod 600 it "
                "(the client's user must still read it)"]
    assert said == (expected if warned else [])
    assert "s3cret" not in caplog.text
