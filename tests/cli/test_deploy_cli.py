"""fleetctl.cli.deploy: what ``up`` records in the fleet (Docker itself is not run here:
the compose deployment is replaced by a recorder; tests/deploy/test_replicas_docker.py runs
the real one)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from fleetctl.cli import deploy as deploy_cli
from fleetctl.cli.main import main
from fleetctl.deploy import composerun
from fleetctl.deploy import operations as ops
from fleetctl.deploy.fleet import load_fleet


@pytest.fixture
def fleet(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    fleet_dir = tmp_path / "fleet"
    ops.create_fleet(fleet_dir)
    ops.add_robot(fleet_dir, "husky1")
    monkeypatch.setenv("FLEET_DIR", str(fleet_dir))
    return fleet_dir


@pytest.fixture
def deployed(monkeypatch: pytest.MonkeyPatch) -> list[composerun.Options]:
    """Every deployment ``up`` asked for (its options), instead of docker compose."""
    calls: list[composerun.Options] = []

    def fake_up(fleet_dir: Path, options: composerun.Options, **_: Any) -> composerun.UpResult:
        calls.append(options)
        urls = tuple(f"ws://10.8.0.1:{8080 + i}/" for i in range(options.replicas))
        return composerun.UpResult(fleet_dir / ".compose/docker-compose.yml", "off",
                                   "https://localhost:8443/", ("husky1",), False,
                                   options.replicas, urls if options.replicas > 1 else ())

    monkeypatch.setattr(deploy_cli, "require_docker", lambda: None)
    monkeypatch.setattr(composerun, "up", fake_up)
    return calls


def _urls(fleet: Path) -> str:
    return (fleet / "robots/husky1/client.yaml").read_text().split("robot_name:")[0]


def test_up_replicas_is_recorded_and_a_plain_up_keeps_it(
        fleet: Path, deployed: list[composerun.Options],
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["up", "--replicas", "2"]) == 0
    out = capsys.readouterr().out
    assert "relay_replicas: 2 recorded in fleet.yaml" in out
    assert "update robots/husky1/client.yaml" in out
    assert load_fleet(fleet).relay_replicas == 2
    assert "- \"ws://10.8.0.1:8081/\"" in _urls(fleet)
    # The next up without --replicas deploys what fleet.yaml says and records nothing.
    assert main(["up", "-o", "json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert [o.replicas for o in deployed] == [2, 2]
    assert result["replicas"] == 2 and result["relay_replicas_recorded"] is False
    # Back to one server: the robots' client.yaml name it alone again.
    assert main(["up", "--replicas", "1"]) == 0
    assert load_fleet(fleet).relay_replicas == 1
    assert _urls(fleet).count("ws://") == 1


def test_a_failed_up_records_nothing(fleet: Path, monkeypatch: pytest.MonkeyPatch,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    from fleetctl.errors import ConflictError

    def refused(*_: Any, **__: Any) -> composerun.UpResult:
        raise ConflictError("the fleet runs with replicas=1, not 2; run `fleetctl down`")

    monkeypatch.setattr(deploy_cli, "require_docker", lambda: None)
    monkeypatch.setattr(composerun, "up", refused)
    before = (fleet / "fleet.yaml").read_bytes()
    assert main(["up", "--replicas", "2"]) == 4
    assert "run `fleetctl down`" in capsys.readouterr().err
    assert (fleet / "fleet.yaml").read_bytes() == before


def test_what_would_stop_the_recording_stops_up_before_it_deploys(
        fleet: Path, deployed: list[composerun.Options],
        capsys: pytest.CaptureFixture[str]) -> None:
    config = fleet / "robots/husky1/client.yaml"
    config.write_text(config.read_text() + "# mine\n")
    assert main(["up", "--replicas", "2"]) == 3
    assert "client.yaml was edited by hand" in capsys.readouterr().err
    assert deployed == [] and load_fleet(fleet).relay_replicas == 1


def test_a_bad_wireguard_mode_is_a_usage_error(
        fleet: Path, deployed: list[composerun.Options],
        capsys: pytest.CaptureFixture[str]) -> None:
    """Exit 2 like every other bad option value (an unknown role, a port out of range)."""
    assert main(["up", "--wireguard", "maybe"]) == 2
    assert capsys.readouterr().err == (
        "fleetctl: error: --wireguard must be auto, on or off, not 'maybe'\n")
    assert deployed == []


@pytest.mark.parametrize(("args", "option"), [
    (["up", "--https-port", "8_443"], "--https-port"),
    (["up", "--https-port", "\uff18\uff14\uff14\uff13"], "--https-port"),  # full-width 8443
    (["up", "--https-port", "70000"], "--https-port"),
    (["up", "--replicas", "\uff12"], "--replicas"),
    (["up", "--replicas", "9"], "--replicas"),
    (["webviz", "--port", "8_000"], "--port"),
    (["demo", "--port", "\uff18\uff10\uff18\uff10"], "--port"),
    (["demo", "--webviz-port", "65536"], "--webviz-port"),
    (["demo", "--robots", "1_0"], "--robots"),
    (["demo", "--base-domain-id", "233"], "--base-domain-id"),
])
def test_integer_options_are_ascii_digits_in_range_everywhere(
        fleet: Path, deployed: list[composerun.Options], args: list[str], option: str,
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """operator.md: an option that is not ASCII digits, or out of range, is exit 2 naming
    it. init's ports were; up/webviz/demo used click's int, which takes 8_443 and
    full-width digits (up then deployed on port 8443)."""
    started: list[object] = []  # were the value taken, webviz and demo would run for good
    monkeypatch.setattr("fleetctl.cli.webviz.run_webviz", lambda *a, **k: started.append(a))
    monkeypatch.setattr("fleetctl.demo.run.run_demo", lambda *a, **k: started.append(a) or 0)
    assert main(args) == 2
    err = " ".join(capsys.readouterr().err.replace("\u2502", " ").split())  # the box's text
    assert f"Invalid value for '{option}'" in err
    assert "is not an integer (ASCII digits)" in err or " is not in " in err
    assert deployed == [] and started == []


def test_status_exits_1_after_its_report_when_the_fleet_is_not_healthy(
        fleet: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A script or a monitoring check reads the exit status; it was 0 however the fleet
    was (a crash-looping server included)."""
    reports = iter([
        composerun.StatusReport((composerun.ServiceState("server", "running", "healthy", 0),
                                 composerun.ServiceState("robot-husky1", "running", "none", 0)),
                                []),
        composerun.StatusReport((composerun.ServiceState("server", "restarting", "starting", 3),
                                 composerun.ServiceState("robot-husky1", "running", "none", 0)),
                                None, "the server does not answer"),
        composerun.StatusReport((), None, "no server container"),
    ])
    monkeypatch.setattr(deploy_cli, "require_docker", lambda: None)
    monkeypatch.setattr(composerun, "existing_options", lambda *_: None)
    monkeypatch.setattr(composerun, "status", lambda *_: next(reports))
    assert main(["status"]) == 0
    capsys.readouterr()
    assert main(["status", "-o", "json"]) == 1
    out, err = capsys.readouterr()
    assert json.loads(out)["healthy"] is False  # the report is still there, whole
    assert err == ("fleetctl: error: the fleet is not healthy: server restarting (starting), "
                   "3 restarts\n")
    assert main(["status"]) == 1
    out, err = capsys.readouterr()
    assert "(no containers: the fleet is not running)" in out
    assert err == ("fleetctl: error: the fleet is not healthy: no containers: the fleet is "
                   "not running\n")


def test_down_help_says_delete_data_deletes_the_recordings(
        capsys: pytest.CaptureFixture[str]) -> None:
    """It named the registry and sessions only; the recordings live in the same volume."""
    assert main(["down", "-h"]) == 0
    text = " ".join(capsys.readouterr().out.replace("\u2502", " ").split())
    assert "robot registry, sessions and the server's MCAP recordings" in text
