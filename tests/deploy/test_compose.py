"""Rendering and running the compose deployment of a real fleet directory (made by
`fleetctl init`), with the docker CLI replaced by a recorder (no Docker needed)."""

from __future__ import annotations

import errno
import json
import re
import shutil
import stat
import subprocess
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import pytest
import yaml

from fleetctl.cli.main import main
from fleetctl.deploy import compose, composerun, hostports, live, tls
from fleetctl.deploy import operations as ops
from fleetctl.deploy.compose import Options
from fleetctl.deploy.dockercli import Completed
from fleetctl.deploy.files import WriteFailed
from fleetctl.deploy.keys import SystemKeySource
from fleetctl.errors import ConfigError, ConflictError, EnvironmentMissing, ExitCode, FleetError


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    fleet_dir = tmp_path / "yard"
    assert main(["init", str(fleet_dir), "--endpoint", "fleet.example:51820"]) == 0
    for name, ip in (("husky1", "10.8.0.2"), ("jackal2", "10.8.0.3")):
        assert main(["add-robot", name, "--ip", ip, "--fleet", str(fleet_dir)]) == 0
    return fleet_dir


def _opts(fleet: Path, **kw: object) -> Options:
    return composerun.default_options(fleet, **kw)


def test_plan_reads_robots_addresses_and_the_https_listener(fleet: Path) -> None:
    plan = compose.plan_for(fleet, _opts(fleet, wireguard="off"))
    assert [(r.name, r.fleet_ip) for r in plan.robots] == [
        ("husky1", "10.8.0.2"), ("jackal2", "10.8.0.3")]
    assert (plan.server_ip, plan.fleet_subnet, plan.server_port, plan.https_port) == (
        "10.8.0.1", "10.8.0.0/24", 8080, 8443)
    assert plan.project.startswith("fleetctlyard") and len(plan.project) == 18
    # Same directory name elsewhere: another project, never the same containers.
    assert compose.project_name(fleet.parent / "other" / "yard") != plan.project
    assert plan.tls_cert.is_file() and plan.tls_key.is_file()
    assert plan.url == "https://fleet.example:8443/"  # the endpoint's host


@pytest.mark.parametrize(("endpoint", "bind", "url"), [
    ("fleet.example:51820", "0.0.0.0", "https://fleet.example:8443/"),
    ("fleet.example:51820", "::", "https://fleet.example:8443/"),
    ("203.0.113.7:4500", "0.0.0.0", "https://203.0.113.7:8443/"),
    ("[2001:db8::5]:51820", "0.0.0.0", "https://[2001:db8::5]:8443/"),
    (None, "0.0.0.0", "https://localhost:8443/"),
    # Published on one address only: the endpoint's host would not reach it.
    ("fleet.example:51820", "127.0.0.1", "https://127.0.0.1:8443/"),
    ("fleet.example:51820", "::1", "https://[::1]:8443/"),
])
def test_the_page_url_is_on_the_host_people_reach(
        tmp_path: Path, endpoint: str | None, bind: str, url: str) -> None:
    """`up` printed https://localhost:PORT/ in a fleet whose endpoint names the server
    host: the URL to open (and to give `recordings --server`) from any other machine is
    on the endpoint's host, which the self-signed certificate also carries."""
    fleet_dir = tmp_path / "yard"
    assert main(["init", str(fleet_dir),
                 *(["--endpoint", endpoint] if endpoint else [])]) == 0
    plan = compose.plan_for(fleet_dir, _opts(fleet_dir, wireguard="off", bind=bind))
    assert plan.url == url


def test_without_sim_only_the_server_runs_and_publishes_one_https_port(fleet: Path) -> None:
    plan = compose.plan_for(fleet, _opts(fleet, wireguard="off", bind="127.0.0.1",
                                          https_port=9443))
    doc = compose.render(plan)
    assert set(doc["services"]) == {"server"}
    server = doc["services"]["server"]
    assert server["ports"] == ["127.0.0.1:9443:8443/tcp"]
    assert server["user"] == "root"  # until the entrypoint hands over secrets and drops
    assert "server-data:/var/lib/fleetctl" in server["volumes"]
    assert plan.url == "https://127.0.0.1:9443/"


def test_plain_mode_puts_simulated_robots_on_their_fleet_ips(fleet: Path) -> None:
    doc = compose.render(compose.plan_for(fleet, _opts(fleet, wireguard="off", sim=True)))
    assert doc["version"] == "2.4"
    assert set(doc["services"]) == {"server", "robot-husky1", "robot-jackal2"}
    robot = doc["services"]["robot-husky1"]
    assert robot["networks"]["fleet"] == {"ipv4_address": "10.8.0.2"}
    assert doc["services"]["server"]["networks"]["fleet"] == {"ipv4_address": "10.8.0.1"}
    ipam = doc["networks"]["fleet"]["ipam"]["config"][0]
    assert ipam == {"subnet": "10.8.0.0/24", "gateway": "10.8.0.254"}
    assert "cap_add" not in robot and "WG_CONFIG" not in robot["environment"]
    assert robot["depends_on"] == {"server": {"condition": "service_healthy"}}
    # The robot's name reaches the shell as a positional parameter, not inside the script.
    assert robot["command"][0:2] == ["bash", "-c"] and "husky1" not in robot["command"][2]
    assert robot["command"][3:5] == ["fleetctl-sim", "husky1"]


def test_wireguard_mode_publishes_udp_and_rewrites_the_endpoint(fleet: Path) -> None:
    plan = compose.plan_for(fleet, _opts(fleet, wireguard="auto", sim=True))
    if not plan.wireguard:
        pytest.skip("no /dev/net/tun on this host")
    doc = compose.render(plan)
    robot, server = doc["services"]["robot-husky1"], doc["services"]["server"]
    assert robot["cap_add"] == ["NET_ADMIN"] and robot["user"] == "root"
    assert robot["environment"]["WG_CONFIG"] == "/etc/fleetctl/wg/wg0.conf"
    assert server["environment"]["WG_REQUIRED"] == "1"
    assert server["environment"]["WG_CONFIG"] == compose.SERVER_WG_CONF
    assert "0.0.0.0:51820:51820/udp" in server["ports"]
    compose.write_files(plan)
    conf = plan.compose_dir / "robots" / "husky1" / "wg0.conf"
    assert "Endpoint = server:51820" in conf.read_text()
    assert "fleet.example" not in conf.read_text()
    for secret in (conf, plan.compose_dir / "secrets" / "tls.key"):
        assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert stat.S_IMODE(plan.compose_dir.stat().st_mode) == 0o700


def test_recordings_go_to_the_data_volume_of_each_relay(fleet: Path) -> None:
    from fleetctl.deploy import composereplicas

    path = fleet / "fleet.yaml"
    path.write_text(path.read_text() + 'recording:\n  topics: ["/.*/map"]\n')
    ops.render_fleet(fleet)
    plan = compose.plan_for(fleet, _opts(fleet, wireguard="off"))
    cfg = compose.container_server_config(plan)
    # On the named volume beside the database, so that `down` and a new image keep them.
    assert cfg["recording"]["directory"] == "/var/lib/fleetctl/recordings"
    assert cfg["recording"]["rules"] == [{"topic": "/.*/map"}]
    assert "server-data:/var/lib/fleetctl" in compose.render(plan)["services"]["server"][
        "volumes"]
    replicated = compose.plan_for(fleet, _opts(fleet, wireguard="off", replicas=2))
    relay = composereplicas.relay_config(replicated, 1, "relay-2")
    assert relay["recording"]["directory"] == "/var/lib/fleetctl/recordings"
    # `up` says what it records.
    result = composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                           runner=FakeDocker())
    assert result.recording_topics == ("/.*/map",)
    # ... and how to list them: the line printed lacked --ca-file, so as printed it failed
    # on the fleet's self-signed certificate; with replicas it named only the first.
    cert = fleet.resolve() / "server" / "tls" / "cert.pem"
    assert result.recordings_command == (
        f"fleetctl recordings list --server {result.url} --token-file FILE --ca-file {cert}")
    two = compose.plan_for(fleet, _opts(fleet, wireguard="off", replicas=2))
    servers = composereplicas.page_urls(two)
    assert composerun.recordings_command(two, tuple(servers)) == (
        f"fleetctl recordings list --server {servers[0]} --server {servers[1]} "
        f"--token-file FILE --ca-file {cert}")


def test_robot_config_without_endpoint_gets_one_inside_compose(fleet: Path) -> None:
    plan = compose.plan_for(fleet, _opts(fleet, wireguard="off", sim=True))
    robot = plan.robots[0]
    conf = robot.robot_dir / "wireguard" / "wg0.conf"
    conf.write_text("\n".join(line for line in conf.read_text().splitlines()
                              if not line.startswith("Endpoint")) + "\n")
    text = compose.robot_wireguard(plan, robot)
    assert text.count("Endpoint = server:51820") == 1
    assert text.index("PublicKey") < text.index("Endpoint")


def test_container_server_config_binds_plain_ws_inside_the_tunnel_only(fleet: Path) -> None:
    plan = compose.plan_for(fleet, _opts(fleet, wireguard="off"))
    wg_plan = replace(plan, wireguard=True)
    cfg = compose.container_server_config(wg_plan)
    assert cfg["listen_host"] == ["10.8.0.1", "127.0.0.1"]
    assert compose.container_server_config(plan)["listen_host"] == "0.0.0.0"
    assert cfg["database"] == "/var/lib/fleetctl/fleet.db"
    # Live from the fleet directory: the server reloads it when fleetctl changes it.
    assert cfg["auth_map"] == "/etc/fleetctl/fleet/auth.yaml"
    assert cfg["web"]["tls_key"] == "/run/fleetctl/secrets/tls.key"
    assert cfg["web"]["tls_cert"] == "/etc/fleetctl/run/tls-cert.pem"
    path = compose.write_files(plan)
    assert yaml.safe_load(path.read_text()) == compose.render(plan)
    assert compose.saved_options(fleet) == plan.options


@pytest.mark.skipif(shutil.which("docker-compose") is None, reason="needs docker-compose")
def test_compose_v1_accepts_the_file(fleet: Path) -> None:
    path = compose.write_files(compose.plan_for(fleet, _opts(fleet, wireguard="off", sim=True)))
    res = subprocess.run(["docker-compose", "-f", str(path), "config", "-q"],
                         capture_output=True, text=True, check=False)
    assert res.returncode == 0, res.stderr


def test_bad_fleet_dirs_are_named(tmp_path: Path, fleet: Path) -> None:
    with pytest.raises(ConfigError, match=r"fleet\.yaml: missing"):
        compose.plan_for(tmp_path)
    with pytest.raises(ConfigError, match="is not a fleet directory"):
        composerun.existing_options(tmp_path)
    with pytest.raises(FleetError, match="no deployment here; run `fleetctl up"):
        composerun.existing_options(fleet)
    (fleet / "robots" / "husky1" / "wireguard" / "wg0.conf").write_text("[Interface]\n")
    with pytest.raises(ConfigError, match=r"wg0.conf: field Address: missing"):
        compose.plan_for(fleet, _opts(fleet, wireguard="off"))


@pytest.mark.parametrize(("dirname", "shown"), [("my:fleet", "':'"), ("my$HOME", "'$'")])
def test_a_fleet_path_compose_cannot_mount_is_named(tmp_path: Path, dirname: str,
                                                     shown: str) -> None:
    fleet_dir = tmp_path / dirname
    ops.create_fleet(fleet_dir, endpoint="fleet.example:51820")
    with pytest.raises(ConfigError, match=re.escape(f"path has {shown}, which a docker")):
        compose.plan_for(fleet_dir, _opts(fleet_dir, wireguard="off"))


def test_a_server_config_without_https_is_named(fleet: Path) -> None:
    server_yaml = fleet / "server" / "server.yaml"
    data = yaml.safe_load(server_yaml.read_text())
    data["web"]["tls_cert"] = "nowhere.pem"
    server_yaml.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"server.yaml: field web.tls_cert: .*does not exist"):
        compose.plan_for(fleet, _opts(fleet, wireguard="off"))
    del data["web"]
    server_yaml.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"field web: missing.*fleetctl render"):
        compose.plan_for(fleet, _opts(fleet, wireguard="off"))


def test_a_corrupt_state_file_is_named(fleet: Path) -> None:
    (fleet / ".compose").mkdir()
    (fleet / ".compose" / "state.json").write_text("{not json")
    with pytest.raises(ConfigError, match=r"state.json: unreadable deployment state"):
        composerun.existing_options(fleet)


@pytest.mark.parametrize(("field", "value"), [
    ("project", "Bad/Name"), ("project", 5), ("wireguard", "maybe"), ("sim", "yes"),
    ("bind", "0.0.0.0:8443:8443"), ("bind", 7), ("https_port", 0), ("https_port", True),
    ("version", "1.0; rm -rf /"), ("replicas", 9), ("fleet_dir", "yard"), ("fleet_dir", 5),
    ("fleet_dir", "/srv/a\0b")])
def test_a_state_file_with_values_up_never_saves_is_named(
        fleet: Path, field: str, value: object) -> None:
    """down/status/logs passed state.json's project and bind on as they were: a damaged or
    edited one gave Compose `-p Bad/Name` (its project `badname`, maybe another fleet's)."""
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                  runner=FakeDocker())
    state = fleet / ".compose" / "state.json"
    data = json.loads(state.read_text())
    state.write_text(json.dumps({**data, field: value}))
    with pytest.raises(ConfigError, match=rf"state.json: unreadable deployment state "
                                          rf"\({field}: "):
        composerun.existing_options(fleet)


def test_wireguard_mode_choice(tmp_path: Path) -> None:
    absent = tmp_path / "tun"
    assert compose.wireguard_mode("off", absent)[0] is False
    on, note = compose.wireguard_mode("auto", absent)
    assert on is False and note.startswith("WARNING: WireGuard NOT used")
    with pytest.raises(EnvironmentMissing):
        compose.wireguard_mode("on", absent)
    absent.write_text("")
    assert compose.wireguard_mode("auto", absent)[0] is True
    with pytest.raises(FleetError, match="auto, on or off"):
        compose.wireguard_mode("maybe", absent)


@pytest.fixture(autouse=True)
def host_ports_free(monkeypatch: pytest.MonkeyPatch) -> None:
    """`up` with a fake docker must not depend on what this machine's ports hold (a real
    fleet may be up on 8443 beside the tests); tests/deploy/test_hostports.py binds real
    sockets, and the Docker life-cycle test runs the real check."""
    monkeypatch.setattr(hostports, "bind_error", lambda *_: None)


class FakeDocker:
    """Records docker commands; answers `ps` with a running server when told to."""

    def __init__(self, *, server_running: bool = False, images: bool = True) -> None:
        self.calls: list[list[str]] = []
        self.server_running = server_running
        self.images = images

    def __call__(self, argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        argv = list(argv)
        self.calls.append(argv)
        out, code = "", 0
        if argv[:2] == ["docker", "ps"] and self.server_running:
            out = "abc123\n"
        elif argv[:3] == ["docker", "image", "inspect"]:
            code = 0 if self.images else 1
        elif argv[:2] == ["docker", "compose"]:
            code = 0
        return Completed(tuple(argv), code, out, "")

    def compose_calls(self) -> list[list[str]]:
        return [c for c in self.calls if c[:2] == ["docker", "compose"] and "version" not in c]


def test_down_keeps_the_data_volume_unless_asked(fleet: Path) -> None:
    docker = FakeDocker()
    opts = _opts(fleet, wireguard="off")
    composerun.down(fleet, opts, progress=lambda _: None, runner=docker)
    composerun.down(fleet, opts, delete_data=True, progress=lambda _: None, runner=docker)
    keep, delete = docker.compose_calls()
    assert "down" in keep and "-v" not in keep
    assert "down" in delete and "-v" in delete


class OtherFleets(FakeDocker):
    """`docker ps -a` of a project answers which compose files made its containers."""

    def __init__(self, made_from: dict[str, list[str]]) -> None:
        super().__init__()
        self.made_from = made_from

    def __call__(self, argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        argv = list(argv)
        if argv[:3] == ["docker", "ps", "-a"]:
            self.calls.append(argv)
            project = argv[argv.index("--filter") + 1].rpartition("=")[2]
            return Completed(tuple(argv), 0, "".join(f + "\n" for f in
                                                     self.made_from.get(project, [])), "")
        return super().__call__(argv, stdin, capture)


def test_down_with_another_fleets_project_is_refused(fleet: Path, tmp_path: Path) -> None:
    """`compose -p P -f OURS down -v` stops every container of project P and deletes P's
    volumes, whichever fleet made them: `down --project P` from the wrong fleet directory
    took another fleet down, and with --delete-data its data."""
    ours = str(fleet.resolve() / ".compose" / "docker-compose.yml")
    theirs = str(tmp_path / "other" / ".compose" / "docker-compose.yml")
    docker = OtherFleets({"theirs": [theirs, theirs], "mine": [ours], "gone": []})
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None, runner=docker)
    recorded = composerun.existing_options(fleet)
    for project, delete_data in (("theirs", False), ("theirs", True), ("gone", True)):
        before = len(docker.compose_calls())
        with pytest.raises(ConflictError, match=f"--project {project}: ") as err:
            composerun.down(fleet, replace(recorded, project=project), delete_data=delete_data,
                            progress=lambda _: None, runner=docker)
        assert (theirs in str(err.value)) == (project == "theirs")
        assert len(docker.compose_calls()) == before  # compose never ran
    # What up recorded, containers this fleet's file made, and a project with no container
    # left (nothing to delete but the containers compose finds: none) go down.
    for project, delete_data in ((recorded.project, True), ("mine", True), ("gone", False)):
        composerun.down(fleet, replace(recorded, project=project), delete_data=delete_data,
                        progress=lambda _: None, runner=docker)
        assert docker.compose_calls()[-1][docker.compose_calls()[-1].index("-p") + 1] == project


@pytest.mark.parametrize("command", ["down", "status", "logs"])
def test_a_project_name_compose_would_change_is_refused_everywhere(
        fleet: Path, command: str, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Only `up` checked --project: `down --project Bad/Name` ran compose, which made it
    project `badname` (maybe another fleet's)."""
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                  runner=FakeDocker())
    monkeypatch.setattr("fleetctl.cli.deploy.require_docker", lambda: None)
    ran: list[object] = []
    for name in ("down", "status", "logs"):
        monkeypatch.setattr(composerun, name, lambda *a, _n=name, **k: ran.append(_n))
    assert main([command, "--fleet", str(fleet), "--project", "Bad/Name"]) == 3
    assert capsys.readouterr().err == ("fleetctl: error: --project 'Bad/Name': expected 1-63 "
                                       "of a-z 0-9 _ - (starting with a letter or digit)\n")
    assert ran == []


def test_logs_of_a_fleet_without_containers_says_so(
        fleet: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """After `down`, compose printed "Attaching to" and exited 0: no word of why."""
    docker = FakeDocker()
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None, runner=docker)
    ran: list[object] = []
    monkeypatch.setattr(composerun.subprocess, "run", lambda *a, **k: ran.append(a))
    options = composerun.existing_options(fleet)
    with pytest.raises(FleetError, match=r"^logs: fleetctlyard\w+ has no containers: the "
                                         r"fleet is not running \(`fleetctl down` removes"):
        composerun.logs(fleet, options, [], follow=False, runner=docker)
    assert ran == []
    ps = docker.calls[-1]
    assert ps[:4] == ["docker", "ps", "-a", "-q"] and f"label=com.docker.compose.project.config_" \
        f"files={fleet.resolve()}/.compose/docker-compose.yml" in ps
    docker.server_running = True  # a container, running or stopped: compose shows its logs
    monkeypatch.setattr(composerun.subprocess, "run",
                        lambda *a, **k: ran.append(a) or subprocess.CompletedProcess(a, 0))
    assert composerun.logs(fleet, options, ["server"], follow=False, runner=docker) == 0
    assert list(ran[-1][0])[-3:] == ["logs", "--no-color", "server"]  # type: ignore[index]


@pytest.mark.parametrize("command", ["down", "status", "logs"])
def test_deploy_commands_in_a_directory_that_is_no_fleet_exit_3(
        tmp_path: Path, command: str, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """As `up`, `list` and every other command: it was exit 1, "no deployment here"."""
    monkeypatch.setattr("fleetctl.cli.deploy.require_docker", lambda: None)
    assert main([command, "--fleet", str(tmp_path)]) == 3
    assert capsys.readouterr().err == (
        f"fleetctl: error: {tmp_path}/fleet.yaml: not found: {tmp_path} is not a fleet "
        "directory (create one with 'fleetctl init', or set --fleet / FLEET_DIR)\n")


@pytest.mark.parametrize("linked", [".compose", ".compose/secrets", ".compose/robots/husky1"])
def test_up_never_writes_secrets_through_a_linked_directory(
        fleet: Path, tmp_path: Path, linked: str) -> None:
    """A link at FLEET/.compose/secrets had `up` copy the TLS private key into the
    directory it points to, and chmod that directory 0700."""
    # With WireGuard (no TUN device needed to write the files): robots' wg0.conf too.
    plan = replace(compose.plan_for(fleet, _opts(fleet, wireguard="off", sim=True)),
                   wireguard=True)
    compose.write_files(plan)
    elsewhere = tmp_path / "elsewhere"
    shutil.move(fleet / linked, elsewhere)
    for p in (elsewhere, *elsewhere.rglob("*")):
        if p.is_file():
            p.unlink()
    elsewhere.chmod(0o755)
    (fleet / linked).symlink_to(elsewhere)
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(fleet.resolve() / linked))} is a "
                                          r"symbolic link \(to .*\), which fleetctl never"):
        compose.write_files(plan)
    assert not [p for p in elsewhere.rglob("*") if p.is_file()]
    assert stat.S_IMODE(elsewhere.stat().st_mode) == 0o755


@pytest.mark.skipif(shutil.which("docker") is None, reason="needs the docker CLI")
@pytest.mark.parametrize("command", [["down"], ["up"], ["status"], ["logs"],
                                     ["down", "--delete-data"]])
def test_deploy_commands_without_a_docker_engine_are_one_line(
        fleet: Path, tmp_path: Path, command: list[str], capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """`down` with no engine at DOCKER_HOST printed compose v1's Python traceback (60 lines)
    before fleetctl's own `compose down failed`."""
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                  runner=FakeDocker())
    socket = tmp_path / "no-engine.sock"
    monkeypatch.setenv("DOCKER_HOST", f"unix://{socket}")
    assert main([*command, "--fleet", str(fleet)]) == 5
    out, err = capsys.readouterr()
    assert err.startswith("fleetctl: error: cannot reach the Docker engine: Cannot connect to "
                          f"the Docker daemon at unix://{socket}")
    assert err.count("\n") == 1 and "Traceback" not in out + err


@pytest.mark.skipif(shutil.which("docker") is None, reason="needs the docker CLI")
def test_a_change_with_no_docker_engine_says_the_deployment_was_not_checked(
        fleet: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """add-robot & co. with no engine at DOCKER_HOST said nothing (a failing `docker ps` read
    as "not running"), and with no docker command at all exited 5 after making the
    change, as if it had failed."""
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                  runner=FakeDocker())
    ops.add_robot(fleet, "rover3")
    monkeypatch.setenv("DOCKER_HOST", f"unix://{tmp_path / 'no-engine.sock'}")
    note = live.sync_running(fleet, lambda _: None)
    assert note is not None and note.startswith(
        "warning: a deployment of this fleet was started here, but Docker cannot be asked "
        "whether it runs (Cannot connect to the Docker daemon at unix://")
    assert note.endswith("run `fleetctl up` with its options once Docker answers (auth.yaml "
                         "reaches a running server by itself)")
    monkeypatch.setenv("PATH", str(tmp_path))  # no docker command at all
    note = live.sync_running(fleet, lambda _: None)
    assert note is not None and "(docker: command not found)" in note


def test_up_needs_the_images(fleet: Path) -> None:
    with pytest.raises(EnvironmentMissing, match=r"fleetctl/server:.* not found.*fleetctl build"):
        composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                      runner=FakeDocker(images=False))
    assert not (fleet / ".compose").exists()


def test_up_refuses_a_server_yaml_the_server_would_refuse(fleet: Path) -> None:
    """server/server.yaml edited by hand with a value the server refuses: `up` said `fleet
    is up` (exit 0) while the server restarted every few seconds, its reason only in the
    logs."""
    path = fleet / "server" / "server.yaml"
    path.write_text(path.read_text().replace("max_subscriptions_per_connection: 256",
                                             "max_subscriptions_per_connection: lots"))
    docker = FakeDocker()
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(path))}: field "
                       r"'limits.max_subscriptions_per_connection' must be a positive integer"):
        composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                      runner=docker)
    assert docker.compose_calls() == [] and not (fleet / ".compose").exists()


def test_up_in_a_fleet_directory_it_cannot_write_in_is_one_line(fleet: Path) -> None:
    """FLEET/.compose could not be made (the fleet directory on a read-only mount, owned by
    another user; here a file in its place): `up` printed mkdir's traceback."""
    (fleet / ".compose").mkdir()
    (fleet / ".compose" / "server").write_text("not a directory\n")
    with pytest.raises(WriteFailed) as info:
        composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                      runner=FakeDocker(), port_probe=lambda *_: None)
    assert str(info.value) == (f"{fleet}/.compose/server: cannot write: File exists; "
                               "nothing was changed")
    assert info.value.exit_code is ExitCode.ENVIRONMENT


def test_up_names_a_compose_directory_that_is_a_file(fleet: Path) -> None:
    """FLEET/.compose a regular file: `up` said `cannot write: File exists` (exit 5), not
    what the path should be."""
    (fleet / ".compose").write_text("not a directory\n")
    with pytest.raises(ConfigError) as info:
        composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                      runner=FakeDocker(), port_probe=lambda *_: None)
    assert str(info.value).startswith(f"{fleet}/.compose: not a directory but a file (it "
                                      "holds the deployment's files, made by `fleetctl up`")


def test_up_refuses_to_change_the_mode_of_a_running_fleet(fleet: Path) -> None:
    docker = FakeDocker()
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None, runner=docker)
    before = (fleet / ".compose" / "docker-compose.yml").read_text()
    docker.server_running = True
    # In the options the operator typed (it said "runs with sim=False, not True").
    with pytest.raises(ConflictError, match=r"runs without --sim, not with --sim;.*same options"
                                            r".*fleetctl down"):
        composerun.up(fleet, _opts(fleet, wireguard="off", sim=True), progress=lambda _: None,
                      runner=docker)
    with pytest.raises(ConflictError, match=r"with --wireguard off, not with --wireguard auto"):
        composerun.up(fleet, _opts(fleet), progress=lambda _: None, runner=docker)
    assert (fleet / ".compose" / "docker-compose.yml").read_text() == before


def test_live_sync_does_nothing_without_a_deployment(fleet: Path) -> None:
    docker = FakeDocker(server_running=True)
    assert live.sync_running(fleet, lambda _: None, runner=docker) is None
    assert docker.calls == []


def test_live_sync_reloads_peers_and_adds_simulated_robots(fleet: Path) -> None:
    docker = FakeDocker()
    composerun.up(fleet, _opts(fleet, wireguard="off", sim=True), progress=lambda _: None,
                  runner=docker)
    ops.add_robot(fleet, "rover3")
    docker.server_running = True
    note = live.sync_running(fleet, lambda _: None, runner=docker)
    assert note is not None and "wg syncconf" not in note
    assert any("wg syncconf wg0" in " ".join(c) for c in docker.calls)
    # Only this fleet's containers: those compose made from this fleet's file.
    mine = f"label=com.docker.compose.project.config_files={fleet.resolve()}/.compose/"
    # (Reading which compose files the project's containers came from names them only.)
    assert all(mine in " ".join(c) for c in docker.calls
               if c[:2] == ["docker", "ps"] and "--format" not in c)
    doc = yaml.safe_load((fleet / ".compose" / "docker-compose.yml").read_text())
    assert "robot-rover3" in doc["services"]
    # Only the simulated robots are brought up to date: a server whose image was rebuilt
    # since is not recreated by an add-robot.
    live_up = docker.compose_calls()[-1]
    assert live_up[-4:] == ["--no-deps", "robot-husky1", "robot-jackal2", "robot-rover3"]
    assert "server" not in live_up[live_up.index("up"):]


def test_live_sync_prints_nothing_but_its_note(fleet: Path) -> None:
    """operator.md: a change to a running fleet adds one note line, not compose's chatter
    (`compose file ...`, `robot-husky1_1 is up-to-date`) after every add-user."""
    captured: list[bool] = []

    class Recording(FakeDocker):
        def __call__(self, argv: Sequence[str], stdin: bytes | None,
                     capture: bool) -> Completed:
            if list(argv[:2]) == ["docker", "compose"] and "up" in argv:
                captured.append(capture)
            return super().__call__(argv, stdin, capture)

    docker = Recording()
    composerun.up(fleet, _opts(fleet, wireguard="off", sim=True), progress=lambda _: None,
                  runner=docker)
    docker.server_running = True
    ops.add_user(fleet, "bob@example.org", "viewer")
    printed: list[str] = []
    note = live.sync_running(fleet, printed.append, runner=docker)
    assert note is not None and "simulated robots updated" not in note  # a user is no robot
    assert printed == [] and captured == [False, True]


class Tunnel(FakeDocker):
    """A server container whose `wg show wg0 peers` answers the peers of the wg0.conf
    `wg syncconf` last loaded (those of the deployment's start before it)."""

    def __init__(self, fleet: Path) -> None:
        super().__init__(server_running=True)
        self.conf = fleet / "server" / "wireguard" / "wg0.conf"
        self.peers = self._conf_peers()

    def _conf_peers(self) -> str:
        return "".join(line.split("=", 1)[1].strip() + "\n"
                       for line in self.conf.read_text().splitlines()
                       if line.replace(" ", "").startswith("PublicKey="))

    def __call__(self, argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        if list(argv[-2:]) == ["wg0", "peers"]:
            self.calls.append(list(argv))
            return Completed(tuple(argv), 0, self.peers, "")
        if "wg syncconf wg0" in " ".join(argv):
            self.peers = self._conf_peers()
        return super().__call__(argv, stdin, capture)


def _changed(outcome: ops.Outcome) -> list[Path]:
    return [c.path for c in outcome.changes]


def test_live_sync_says_only_what_changed(fleet: Path) -> None:
    """`remove-user NAME` on a running fleet said `WireGuard peers synced` (users are token
    identities, no peer changed) and every note `auth.yaml is reloaded`, changed or not."""
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                  runner=FakeDocker())
    docker = Tunnel(fleet)
    added = ops.add_user(fleet, "bob@example.org", "viewer").outcome
    note = live.sync_running(fleet, lambda _: None, runner=docker, changed=_changed(added))
    assert note == ("running fleet: auth.yaml changed: the server reloads it by itself "
                    "(within a second)")
    removed = ops.remove_user(fleet, "bob@example.org").outcome
    note = live.sync_running(fleet, lambda _: None, runner=docker, changed=_changed(removed))
    assert note is not None and "WireGuard" not in note and "auth.yaml changed" in note
    robot = ops.add_robot(fleet, "rover3").outcome
    note = live.sync_running(fleet, lambda _: None, runner=docker, changed=_changed(robot))
    assert note is not None and note.startswith(
        "running fleet: WireGuard peers: 1 added, 0 removed; ")
    gone = ops.remove_robot(fleet, "rover3").outcome
    note = live.sync_running(fleet, lambda _: None, runner=docker, changed=_changed(gone))
    assert note is not None and "WireGuard peers: 0 added, 1 removed" in note
    assert live.sync_running(fleet, lambda _: None, runner=docker,
                             changed=[]) == "running fleet: nothing to apply"


def test_live_sync_after_the_last_robot_goes_leaves_the_server_alone(fleet: Path) -> None:
    docker = FakeDocker()
    composerun.up(fleet, _opts(fleet, wireguard="off", sim=True), progress=lambda _: None,
                  runner=docker)
    docker.server_running = True
    for name in ("husky1", "jackal2"):
        ops.remove_robot(fleet, name)
    live.sync_running(fleet, lambda _: None, runner=docker)
    live_up = docker.compose_calls()[-1]
    assert live_up[live_up.index("up"):] == [
        "up", "-d", "--remove-orphans", "--no-deps", "--no-recreate", "server"]


def test_live_sync_restarts_the_server_only_for_a_new_certificate(fleet: Path) -> None:
    docker = FakeDocker()
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None, runner=docker)
    docker.server_running = True
    live.sync_running(fleet, lambda _: None, runner=docker)
    assert not any(c[:2] == ["docker", "restart"] for c in docker.calls)
    ops.set_endpoint(fleet, "other.example:51820")  # a new self-signed cert for the new name
    note = live.sync_running(fleet, lambda _: None, runner=docker)
    assert note is not None and "new TLS certificate" in note
    assert sum(c[:2] == ["docker", "restart"] for c in docker.calls) == 1
    deployed = fleet / ".compose" / "server" / "tls-cert.pem"
    assert deployed.read_bytes() == (fleet / "server" / "tls" / "cert.pem").read_bytes()


def test_live_sync_restarts_the_server_for_a_new_server_yaml(fleet: Path) -> None:
    docker = FakeDocker()
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None, runner=docker)
    docker.server_running = True
    path = fleet / "fleet.yaml"
    path.write_text(path.read_text() + 'recording:\n  topics: ["/.*/map"]\n')
    ops.render_fleet(fleet)
    note = live.sync_running(fleet, lambda _: None, runner=docker)
    assert note is not None and "restarted with the new server.yaml" in note
    assert sum(c[:2] == ["docker", "restart"] for c in docker.calls) == 1
    deployed = yaml.safe_load((fleet / ".compose" / "server" / "server.yaml").read_text())
    assert deployed["recording"]["directory"] == "/var/lib/fleetctl/recordings"
    live.sync_running(fleet, lambda _: None, runner=docker)  # nothing new: no restart
    assert sum(c[:2] == ["docker", "restart"] for c in docker.calls) == 1


def test_live_sync_recreates_the_server_when_fleet_yaml_moves_its_ports(fleet: Path) -> None:
    """`render` after https_port changed in fleet.yaml restarted the server with the new
    server.yaml: it listened on 9443 behind the container's old 8443 mapping, the page was
    on neither port and `status` said healthy. A restart keeps a container's ports; the
    deployment is brought up to date as `up` would (compose recreates the server)."""
    docker = FakeDocker()
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None, runner=docker)
    docker.server_running = True
    path = fleet / "fleet.yaml"
    path.write_text(path.read_text().replace("https_port: 8443", "https_port: 9443"))
    ops.render_fleet(fleet)
    ups = len(docker.compose_calls())
    note = live.sync_running(fleet, lambda _: None, runner=docker)
    assert note is not None and "server recreated with its new compose definition" in note
    assert not any(c[:2] == ["docker", "restart"] for c in docker.calls)
    full_up = docker.compose_calls()[ups:]
    assert len(full_up) == 1 and full_up[0][full_up[0].index("up"):] == [
        "up", "-d", "--remove-orphans"]
    doc = yaml.safe_load((fleet / ".compose" / "docker-compose.yml").read_text())
    assert doc["services"]["server"]["ports"] == ["0.0.0.0:9443:9443/tcp"]
    live.sync_running(fleet, lambda _: None, runner=docker)  # nothing new: no compose call
    assert len(docker.compose_calls()) == ups + 1


def test_live_sync_of_replicas_recreates_nothing_for_an_add_user(fleet: Path) -> None:
    """The server's compose definition is compared with the deployed one: with replicas
    (NATS passwords and configs kept from the first `up`) an add-user changes none of it."""
    docker = FakeDocker()
    composerun.up(fleet, _opts(fleet, wireguard="off", sim=True, replicas=2),
                  progress=lambda _: None, runner=docker, port_probe=lambda *_: None)
    docker.server_running = True
    ops.add_user(fleet, "bob@example.org", "viewer")
    before = len(docker.compose_calls())
    note = live.sync_running(fleet, lambda _: None, runner=docker)
    assert note is not None and "recreated" not in note
    (live_up,) = docker.compose_calls()[before:]
    assert live_up[live_up.index("up"):] == [
        "up", "-d", "--remove-orphans", "--no-deps", "robot-husky1", "robot-jackal2"]


def test_bind_and_project_are_checked_before_they_reach_compose(fleet: Path) -> None:
    with pytest.raises(ConfigError, match=r"--bind '1.2.3.4:2222:22': expected an IP"):
        _opts(fleet, bind="1.2.3.4:2222:22")
    with pytest.raises(ConfigError, match=r"--project 'x y'"):
        _opts(fleet, project="x y")
    plan = compose.plan_for(fleet, _opts(fleet, wireguard="off", bind="::1"))
    assert compose.render(plan)["services"]["server"]["ports"] == ["[::1]:8443:8443/tcp"]


def test_up_names_a_taken_host_port_before_compose_runs(fleet: Path) -> None:
    def https_taken(host: str, port: int, protocol: str) -> OSError | None:
        return OSError(errno.EADDRINUSE, "Address in use") if protocol == "tcp" else None

    docker = FakeDocker()
    with pytest.raises(ConflictError, match=r"0\.0\.0\.0:8443/tcp \(server\) is in use"):
        composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                      runner=docker, port_probe=https_taken)
    assert docker.compose_calls() == []
    assert not (fleet / ".compose").exists()


def test_up_on_a_running_fleet_does_not_trip_over_its_own_ports(fleet: Path) -> None:
    class PublishingDocker(FakeDocker):
        def __call__(self, argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
            if any("{{.Ports}}" in arg for arg in argv):
                self.calls.append(list(argv))
                made_from = fleet.resolve() / composerun.COMPOSE_DIR / composerun.COMPOSE_FILE
                return Completed(tuple(argv), 0, f"{made_from}\t0.0.0.0:8443->8443/tcp\n", "")
            return super().__call__(argv, stdin, capture)

    def held_by_the_fleet(host: str, port: int, protocol: str) -> OSError | None:
        return OSError(errno.EADDRINUSE, "Address in use")

    docker = PublishingDocker()
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                  runner=docker, port_probe=held_by_the_fleet)
    assert any("up" in call for call in docker.compose_calls())


def test_logs_names_the_services_when_one_is_unknown(fleet: Path) -> None:
    composerun.up(fleet, _opts(fleet, wireguard="off", sim=True), progress=lambda _: None,
                  runner=FakeDocker())
    assert composerun.deployed_services(fleet) == ["robot-husky1", "robot-jackal2", "server"]
    with pytest.raises(ConfigError, match=r"no service 'sever' .*its services: robot-husky1, "
                                          r"robot-jackal2, server"):
        composerun.logs(fleet, _opts(fleet), ["server", "sever"], follow=False)
    assert composerun.deployed_services(fleet / "nowhere") == []
    compose_file = fleet / composerun.COMPOSE_DIR / composerun.COMPOSE_FILE
    compose_file.write_text("services: !!int x\n")  # edited by hand: nothing known
    assert composerun.deployed_services(fleet) == []
    compose_file.write_text("services: {1: {}, server: {}}\n")
    assert composerun.deployed_services(fleet) == ["1", "server"]


def test_status_shows_an_unknown_battery_as_null_and_a_dash() -> None:
    """/robots of a server older than this fleetctl still says -1 for 'no battery topic'."""
    robots = [{"name": "husky1", "online": True, "battery_level": -1.0, "last_seen_s": None},
              {"name": "jackal2", "online": True, "battery_level": 0.8, "last_seen_s": None},
              {"name": "rover3", "online": False, "battery_level": None}]
    report = composerun.StatusReport((), robots)
    assert [r["battery_level"] for r in report.to_json()["robots"]] == [None, 0.8, None]
    lines = report.render_text().splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("ROBOT"))
    assert lines[header].split() == ["ROBOT", "ONLINE", "BATTERY", "LAST", "SEEN"]
    assert [line.split()[:3] for line in lines[header + 1:header + 4]] == [
        ["husky1", "yes", "-"], ["jackal2", "yes", "80%"], ["rover3", "no", "-"]]


def test_status_marks_a_robot_the_fleet_no_longer_has(fleet: Path) -> None:
    """The server's registry keeps a removed robot: `status` showed it offline for good,
    like a robot that is down."""
    ops.add_robot(fleet, "rover3")
    ops.remove_robot(fleet, "rover3")
    robots = [{"name": "husky1", "online": True, "last_seen_s": None},
              {"name": "rover3", "online": False, "last_seen_s": None}]
    report = composerun.StatusReport((), robots,
                                     fleet_robots=composerun._fleet_robot_names(fleet))
    assert report.fleet_robots == {"husky1", "jackal2"}
    assert [r["in_fleet"] for r in report.to_json()["robots"]] == [True, False]
    text = report.render_text()
    assert "rover3" in text and text.split("rover3", 1)[1].splitlines()[0].endswith(
        "-  (not in fleet.yaml: removed)")
    assert "removed" not in text.split("husky1", 1)[1].splitlines()[0]


def test_status_lists_the_fleets_robots_that_never_connected(fleet: Path) -> None:
    """`status` of a fleet whose robots were being set up said "(no robots yet)", as if
    the fleet had none: the server's registry lists only robots it has seen."""
    names = composerun._fleet_robot_names(fleet)
    report = composerun.StatusReport((), [], fleet_robots=names)
    assert report.to_json()["never_connected"] == ["husky1", "jackal2"]
    lines = report.render_text().splitlines()
    header = lines.index(next(line for line in lines if line.startswith("ROBOT")))
    assert [line.split() for line in lines[header + 1:header + 3]] == [
        ["husky1", "no", "-", "never"], ["jackal2", "no", "-", "never"]]
    seen = composerun.StatusReport((), [{"name": "husky1", "online": True}], fleet_robots=names)
    assert seen.to_json()["never_connected"] == ["jackal2"]
    assert "(no robots in fleet.yaml)" in composerun.StatusReport(
        (), [], fleet_robots=frozenset()).render_text()


def test_status_takes_never_connected_robots_from_fleet_yaml_not_the_server() -> None:
    """The server lists the robots its auth map expects and has not seen (for the page);
    status says which never connected from fleet.yaml, as it did before: the server's
    entries for them are left out, not shown twice."""
    body = json.dumps({"robots": [
        {"name": "husky1", "online": True, "last_seen_s": 1.0},
        {"name": "jackal2", "online": False, "never_connected": True, "last_seen_s": None}]})

    def runner(args: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        return Completed(list(args), 0, body, "")

    robots, error = composerun._server_robots("cid", runner)
    assert error == "" and robots == [{"name": "husky1", "online": True, "last_seen_s": 1.0}]
    report = composerun.StatusReport((), robots, fleet_robots=frozenset({"husky1", "jackal2"}))
    assert report.to_json()["never_connected"] == ["jackal2"]
    assert report.render_text().count("jackal2") == 1


def test_status_of_a_moved_fleet_directory_names_where_its_containers_came_from(
        fleet: Path, tmp_path: Path) -> None:
    """The fleet directory moved while its deployment ran: `status` said "no containers:
    the fleet is not running" (none was made from the new path), which was false."""
    docker = FakeDocker()
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None, runner=docker)
    old = str(tmp_path / "before" / ".compose" / "docker-compose.yml")
    project = composerun.existing_options(fleet).project
    report = composerun.status(fleet, composerun.existing_options(fleet),
                               runner=OtherFleets({project: [old, old]}))
    assert report.problems() == [
        f"no containers made from this directory's compose file, but its project has "
        f"containers made from {old} (was the fleet directory moved while it ran? "
        "`fleetctl down` here stops them)"]
    assert f"containers made from {old}" in report.render_text()
    stopped = composerun.status(fleet, composerun.existing_options(fleet),
                                runner=OtherFleets({}))
    assert stopped.problems() == ["no containers: the fleet is not running"]


def test_status_asks_only_for_this_fleets_containers(fleet: Path) -> None:
    """`status --project P` listed every container of project P, another fleet's too."""
    docker = FakeDocker()
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None, runner=docker)
    before = len(docker.calls)
    composerun.status(fleet, composerun.existing_options(fleet, "theirs"), runner=docker)
    mine = (f"label=com.docker.compose.project.config_files={fleet.resolve()}"
            "/.compose/docker-compose.yml")
    # (Reading which compose files the project's containers came from names them only.)
    listings = [c for c in docker.calls[before:] if c[:2] == ["docker", "ps"]
                and "--format" not in c]
    assert listings and all(mine in c and "label=com.docker.compose.project=theirs" in c
                            for c in listings)


class RunningServices(FakeDocker):
    """`docker ps` finds one container per service in *running*, each running and healthy;
    `docker exec` in the server fails (no robot list, no tunnel: not what is tested)."""

    def __init__(self, running: Sequence[str]) -> None:
        super().__init__()
        self.running = list(running)

    def __call__(self, argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        argv = list(argv)
        if argv[:2] == ["docker", "ps"] and "--format" not in argv:
            self.calls.append(argv)
            wanted = [f.rpartition("=")[2] for f in argv
                      if f.startswith("label=com.docker.compose.service=")]
            ids = [f"cid-{s}" for s in self.running if not wanted or s in wanted]
            return Completed(tuple(argv), 0, "".join(i + "\n" for i in ids), "")
        if argv[:2] == ["docker", "inspect"] and argv[2].startswith("cid-"):
            self.calls.append(argv)
            info = {"Config": {"Labels": {"com.docker.compose.service": argv[2][4:]}},
                    "State": {"Status": "running", "Health": {"Status": "healthy"}},
                    "RestartCount": 0}
            return Completed(tuple(argv), 0, json.dumps([info]), "")
        if argv[:2] == ["docker", "exec"]:
            self.calls.append(argv)
            return Completed(tuple(argv), 1, "", "not what is tested")
        return super().__call__(argv, stdin, capture)


def test_status_names_a_service_of_the_deployment_that_has_no_container(
        fleet: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`up --sim` interrupted (Ctrl-C) after compose made the server, or a robot's
    container removed by hand (`docker rm -f`): `status` listed the containers there were,
    said nothing of the missing one and exited 0, so a monitoring check saw a healthy
    fleet with a simulated robot (or a relay replica) gone."""
    composerun.up(fleet, _opts(fleet, wireguard="off", sim=True), progress=lambda _: None,
                  runner=FakeDocker())
    assert composerun.deployed_services(fleet) == ["robot-husky1", "robot-jackal2", "server"]
    options = composerun.existing_options(fleet)
    report = composerun.status(fleet, options, runner=RunningServices(["server",
                                                                       "robot-husky1"]))
    assert not report.healthy
    assert report.problems() == [
        "robot-jackal2 has no container (`fleetctl up` with the options the fleet runs with "
        "makes it again)"]
    assert {"service": "robot-jackal2", "state": "missing", "health": "unknown",
            "restarts": 0} in report.to_json()["services"]
    rows = [line.split() for line in report.render_text().splitlines()[1:4]]
    assert rows == [["robot-husky1", "running", "healthy", "0"],
                    ["robot-jackal2", "missing", "unknown", "0"],
                    ["server", "running", "healthy", "0"]]
    # Every service there: healthy, as before.
    whole = composerun.status(fleet, options, runner=RunningServices(
        ["server", "robot-husky1", "robot-jackal2"]))
    assert whole.healthy and whole.problems() == []
    # No container at all: the fleet is not running, said once (not once per service).
    assert composerun.status(fleet, options, runner=RunningServices([])).problems() == [
        "no containers: the fleet is not running"]


class ProjectVolumes(FakeDocker):
    """`docker volume ls` of a project lists *volumes*; `docker volume rm` removes them."""

    def __init__(self, volumes: Sequence[str]) -> None:
        super().__init__()
        self.volumes = list(volumes)

    def __call__(self, argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        argv = list(argv)
        if argv[:3] == ["docker", "volume", "ls"]:
            self.calls.append(argv)
            project = argv[argv.index("--filter") + 1].rpartition("=")[2]
            mine = [v for v in self.volumes if v.startswith(project + "_")]
            return Completed(tuple(argv), 0, "".join(v + "\n" for v in mine), "")
        if argv[:3] == ["docker", "volume", "rm"]:
            self.calls.append(argv)
            self.volumes = [v for v in self.volumes if v not in argv[3:]]
            return Completed(tuple(argv), 0, "", "")
        return super().__call__(argv, stdin, capture)


def test_down_delete_data_deletes_the_volumes_of_an_earlier_mode(fleet: Path) -> None:
    """`up`, `down`, `up --replicas 2`, `down --delete-data` left the single server's
    `server-data` volume (its registry, sessions and recordings): compose's `down -v`
    deletes only the volumes the current compose file names, and with replicas it names
    `relay-i-data` and `nats-k-data` instead (the other way round left those)."""
    project = composerun.default_options(fleet).project
    other = "fleetctlother123456_server-data"
    docker = ProjectVolumes([f"{project}_server-data", f"{project}_relay-1-data", other])
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None, runner=docker)
    said: list[str] = []
    composerun.down(fleet, composerun.existing_options(fleet), progress=said.append,
                    runner=docker)
    assert len(docker.volumes) == 3  # plain down keeps every volume
    assert not any(c[:3] == ["docker", "volume", "rm"] for c in docker.calls)
    composerun.down(fleet, composerun.existing_options(fleet), delete_data=True,
                    progress=said.append, runner=docker)
    down_v = max(i for i, c in enumerate(docker.calls) if "down" in c and "-v" in c)
    rm = next(i for i, c in enumerate(docker.calls) if c[:3] == ["docker", "volume", "rm"])
    assert rm > down_v  # after compose removed the containers that use them
    assert docker.volumes == [other]  # another project's volume is never touched
    assert any(f"{project}_relay-1-data" in line for line in said)


class WireGuardDump(RunningServices):
    """The server runs; `wg show wg0 dump` answers *dump*."""

    def __init__(self, dump: str) -> None:
        super().__init__(["server"])
        self.dump = dump

    def __call__(self, argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        if list(argv[:2]) == ["docker", "exec"] and "wg" in argv:
            return Completed(tuple(argv), 0, self.dump, "")
        return super().__call__(argv, stdin, capture)


def test_status_lists_tunnel_peers_in_the_robot_table_order(fleet: Path) -> None:
    """The TUNNEL PEER table came in wg's own order (jackal2 above husky1 while the ROBOT
    table above it said husky1, jackal2): the same robots, in the same order in both."""
    composerun.up(fleet, _opts(fleet, wireguard="off"), progress=lambda _: None,
                  runner=FakeDocker())
    now = int(time.time())
    dump = ("PRIV\tPUB\t51820\toff\n"
            f"K3\tPSK\t(none)\t10.8.0.9/32\t0\t0\t0\toff\n"
            f"K2\tPSK\t203.0.113.9:4500\t10.8.0.3/32\t{now - 4}\t10\t20\toff\n"
            f"K1\tPSK\t203.0.113.8:4500\t10.8.0.2/32\t{now - 7}\t10\t20\toff\n")
    report = composerun.status(fleet, composerun.existing_options(fleet),
                               runner=WireGuardDump(dump))
    assert report.tunnel is not None
    assert [(p.robot, p.address) for p in report.tunnel] == [
        ("husky1", "10.8.0.2"), ("jackal2", "10.8.0.3"), ("?", "10.8.0.9")]
    assert report.tunnel[2].handshake_age_s is None
    assert report.tunnel[0].handshake_age_s is not None and report.tunnel[0].handshake_age_s >= 6


def test_status_columns_line_up_with_the_longest_robot_name() -> None:
    """Robot names may have 63 characters: the first column was 24 wide, and the row of a
    longer name (its `robot-NAME` service, its tunnel peer) had every later column
    shifted right, out from under its header."""
    name = "r" + "x" * 62
    services = (composerun.ServiceState(f"robot-{name}", "running", "healthy", 0),
                composerun.ServiceState("server", "running", "healthy", 0))
    robots = [{"name": name, "online": True, "last_seen_s": None},
              {"name": "husky1", "online": False, "last_seen_s": None}]
    tunnel = (composerun.TunnelPeer(name, "10.8.0.2", None),
              composerun.TunnelPeer("husky1", "10.8.0.3", None))
    text = composerun.StatusReport(services, robots, tunnel=tunnel).render_text()
    for block, second in zip(text.split("\n\n")[:3], ("STATE", "ONLINE", "ADDRESS"),
                             strict=True):
        header, *rows = block.splitlines()
        col = header.index(second)
        assert all(row[col - 1] == " " and row[col] != " " for row in rows), block
    short = composerun.StatusReport(services[1:], robots[1:], tunnel=tunnel[1:]).render_text()
    assert short.splitlines()[1] == f"{'server':<24} {'running':<11} {'healthy':<10} 0"


def test_up_says_when_the_certificate_does_not_cover_the_page_host(fleet: Path,
                                                                  tmp_path: Path) -> None:
    """fleet.yaml `tls:` with the operator's certificate for fleet.example.org, endpoint
    fleet.example: `up` printed https://fleet.example:8443/ without a word, and a browser
    warned there."""
    opts = _opts(fleet, wireguard="off", bind="0.0.0.0")
    result = composerun.up(fleet, opts, progress=lambda _: None, runner=FakeDocker(),
                           port_probe=lambda *_: None)
    assert result.url == "https://fleet.example:8443/" and result.certificate_note == ""
    made = tls.self_signed(("fleet.example.org", "192.0.2.7"), SystemKeySource())
    cert, key = tmp_path / "own-cert.pem", tmp_path / "own-key.pem"
    cert.write_bytes(made.cert_pem)
    key.write_text(made.key_pem.reveal())
    key.chmod(0o600)
    path = fleet / "fleet.yaml"
    path.write_text(path.read_text().replace("tls: null\n", f"tls:\n  cert: {cert}\n"
                                             f"  key: {key}\n"))
    ops.render_fleet(fleet)
    result = composerun.up(fleet, opts, progress=lambda _: None, runner=FakeDocker(),
                           port_probe=lambda *_: None)
    assert result.certificate_note == (
        f"the HTTPS certificate {cert} does not cover fleet.example, only fleet.example.org, "
        "192.0.2.7: a browser will warn at this URL; open the page by one of those names if "
        "it reaches this host, or give fleet.yaml tls: a certificate for fleet.example")
    local = compose.plan_for(fleet, replace(opts, bind="127.0.0.1"))
    assert local.url == "https://127.0.0.1:8443/"
    assert "does not cover 127.0.0.1, only" in composerun.certificate_note(local)
