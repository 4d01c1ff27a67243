"""``fleetctl client``: bad configs are reported with file and field, never a traceback."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from fleetctl.cli.main import main
from fleetctl.errors import ExitCode


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
