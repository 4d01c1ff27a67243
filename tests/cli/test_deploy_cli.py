"""fleetctl.cli.deploy: what ``up`` records in the fleet (Docker itself is not run here:
the compose deployment is replaced by a recorder; tests/deploy/test_replicas_docker.py runs
the real one)."""

from __future__ import annotations

import json
from collections.abc import Callable
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
    monkeypatch.setattr(composerun, "wait_started", lambda *_: None)
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


# A stand-in `docker` on PATH for the real `fleetctl up` below: the engine answers, the
# images exist, compose succeeds, nothing runs (tests/deploy/test_lifecycle_docker.py runs
# the real engine).
_STAND_IN_DOCKER = """#!/bin/sh
[ "$1" = version ] && echo 24.0.0
exit 0
"""


def _free_tcp_port() -> int:
    """A port `up`'s host-port check finds free (it binds it itself before compose runs)."""
    import socket

    with socket.socket() as s:
        s.bind(("0.0.0.0", 0))
        return int(s.getsockname()[1])


def _stand_in_fleetctl(tmp_path: Path) -> tuple[Path, Callable[..., Any]]:
    """A fleet path under *tmp_path* and a runner of the real `fleetctl` command (a
    process, FLEET_DIR set) whose `docker` is the stand-in: ``run(*args, code=0)``
    returns the CompletedProcess, having checked its exit code."""
    import os
    import subprocess
    import sys

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "docker").write_text(_STAND_IN_DOCKER)
    (bin_dir / "docker").chmod(0o755)
    fleet = tmp_path / "yard"
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
           "FLEET_DIR": str(fleet)}

    def run(*args: str, code: int = 0) -> subprocess.CompletedProcess[str]:
        done = subprocess.run([sys.executable, "-m", "fleetctl.cli.main", *args], env=env,
                              cwd=tmp_path, capture_output=True, text=True, timeout=120,
                              check=False)
        assert done.returncode == code, done.stderr
        return done

    return fleet, run


@pytest.mark.parametrize(("endpoint", "host"), [("fleet.example.org:51820", "fleet.example.org"),
                                                (None, "localhost")])
def test_up_and_the_recordings_hint_name_the_endpoints_host(
        tmp_path: Path, endpoint: str | None, host: str) -> None:
    """`up` printed https://localhost:PORT/ (and the same in its `recordings list` line)
    in a fleet whose fleet.yaml names the server host: the page's URL is on the endpoint's
    host, localhost only without one; `recordings list --config` of the deployed fleet
    said `--server https://HOST:PORT/` with the container's port, not `up --https-port`'s."""
    fleet, fleetctl = _stand_in_fleetctl(tmp_path)
    fleetctl("init", str(fleet), *(["--endpoint", endpoint] if endpoint else []))
    with (fleet / "fleet.yaml").open("a") as f:
        f.write("recording:\n  topics: ['/.*/odom']\n")
    fleetctl("render")
    port = _free_tcp_port()
    out = fleetctl("up", "--wireguard", "off", "--https-port", str(port)).stdout
    url = f"https://{host}:{port}/"
    cert = fleet.resolve() / "server" / "tls" / "cert.pem"
    assert f"fleet is up: open {url} and sign in" in out and "warning:" not in out
    assert f"(fleetctl recordings list --server {url} --token-file FILE --ca-file {cert})" in out
    config = fleet / "server" / "server.yaml"
    err = fleetctl("recordings", "list", "--config", str(config), code=3).stderr
    assert err.endswith(f"ask it with --server {url} --token-file FILE --ca-file {cert}\n")


@pytest.mark.parametrize(("args", "said"), [
    (["--image", "db"], "--image: unknown image(s) 'db'"),
    (["--mirror", "deb.debian.org/debian"], "--mirror 'deb.debian.org/debian': expected"),
])
def test_build_refuses_bad_options_before_asking_docker(
        args: list[str], said: str, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A typo in `build`'s options is a usage error (exit 2) said at once, with or without
    Docker; `--mirror` was ignored while the base image existed and the build went on."""
    def no_docker() -> None:
        raise AssertionError("docker asked before the options were checked")

    monkeypatch.setattr(deploy_cli, "require_docker", no_docker)
    assert main(["build", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fleetctl: error: ") and said in err and err.count("\n") == 1


def test_up_warns_when_the_fleets_own_certificate_does_not_cover_the_url(
        tmp_path: Path) -> None:
    """fleet.yaml `tls:` with the operator's certificate for another name than the
    endpoint host: `up` printed the page's URL on the endpoint host with no word, and a
    browser warned there."""
    from fleetctl.deploy.keys import SystemKeySource
    from fleetctl.deploy.tls import self_signed

    fleet, run = _stand_in_fleetctl(tmp_path)

    def fleetctl(*args: str) -> str:
        return str(run(*args).stdout)

    fleetctl("init", str(fleet), "--endpoint", "vpn.example.com:51820")
    made = self_signed(("pages.example.org",), SystemKeySource())
    cert, key = tmp_path / "own.pem", tmp_path / "own.key"
    cert.write_bytes(made.cert_pem)
    key.write_text(made.key_pem.reveal())
    key.chmod(0o600)
    path = fleet / "fleet.yaml"
    path.write_text(path.read_text().replace(
        "tls: null\n", f"tls:\n  cert: {cert}\n  key: {key}\n"))
    fleetctl("render")
    port = _free_tcp_port()
    lines = fleetctl("up", "--wireguard", "off", "--bind", "0.0.0.0", "--https-port",
                     str(port)).splitlines()
    first = lines.index(f"fleet is up: open https://vpn.example.com:{port}/ and sign in with "
                        "a user token (`fleetctl add-user`)")
    assert lines[first + 1] == (
        f"warning: the HTTPS certificate {cert} does not cover vpn.example.com, only "
        "pages.example.org: a browser will warn at this URL; open the page by one of those "
        "names if it reaches this host, or give fleet.yaml tls: a certificate for "
        "vpn.example.com")
