"""``up --replicas N`` rendering on a real fleet directory (made by `fleetctl init`): the
gateway, the replicas in its network namespace, the NATS nodes, their configs and secrets
(no Docker needed; the containers run in test_replicas_docker.py)."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import bcrypt
import pytest
import yaml

from fleetctl.cli.main import main
from fleetctl.deploy import compose, composereplicas, composerun, replicas
from fleetctl.deploy.compose import SECRETS_RUN
from fleetctl.errors import ConfigError
from fleetctl.server.cluster.config import parse_cluster


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    fleet_dir = tmp_path / "yard"
    assert main(["init", str(fleet_dir), "--endpoint", "fleet.example:51820"]) == 0
    assert main(["add-robot", "husky1", "--ip", "10.8.0.2", "--fleet", str(fleet_dir)]) == 0
    return fleet_dir


def plan(fleet: Path, **kw: object) -> compose.ComposePlan:
    options = composerun.default_options(fleet, **{"wireguard": "on", "replicas": 3, **kw})
    return compose.plan_for(fleet, options)


def test_replicas_share_the_gateways_namespace_and_each_get_ports(
        fleet: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(compose, "wireguard_mode", lambda _asked: (True, "on"))
    p = plan(fleet, sim=True, bind="127.0.0.1", https_port=9443)
    doc = compose.render(p)
    services = doc["services"]
    assert set(services) == {"server", "relay-1", "relay-2", "relay-3", "nats-1", "nats-2",
                             "nats-3", "robot-husky1"}
    gateway = services["server"]
    assert gateway["ports"] == ["127.0.0.1:9443:8443/tcp", "127.0.0.1:9444:8444/tcp",
                                "127.0.0.1:9445:8445/tcp", "127.0.0.1:51820:51820/udp"]
    assert gateway["environment"]["WG_REQUIRED"] == "1"
    assert gateway["environment"]["FLEETCTL_HEALTH"].split() == [
        f"http://127.0.0.1:{8080 + i}/healthz" for i in range(3)]
    for i, name in enumerate(replicas.replica_names(3)):
        relay = services[name]
        assert relay["network_mode"] == "service:server" and "networks" not in relay
        assert "ports" not in relay
        assert relay["command"][-1].endswith(f"/{name}.yaml")
        assert f"{name}-data:/var/lib/fleetctl" in relay["volumes"]
        assert relay["environment"]["FLEETCTL_HEALTH"] == f"http://127.0.0.1:{8080 + i}/healthz"
        assert set(relay["depends_on"]) == {"server", *replicas.NATS_NODES}
    assert services["nats-1"]["command"][:2] == ["nats-server", "-c"]
    assert set(doc["volumes"]) == {"relay-1-data", "relay-2-data", "relay-3-data",
                                   "nats-1-data", "nats-2-data", "nats-3-data"}
    robot = services["robot-husky1"]
    assert robot["depends_on"] == {"relay-1": {"condition": "service_healthy"}}
    assert any(v.endswith(":/etc/fleetctl/robot/client.yaml:ro") for v in robot["volumes"])


def test_plain_mode_gives_the_nats_nodes_fixed_addresses_away_from_robots(
        fleet: Path) -> None:
    doc = compose.render(plan(fleet, wireguard="off"))
    addresses = {name: svc["networks"]["fleet"]["ipv4_address"]
                 for name, svc in doc["services"].items() if "networks" in svc}
    assert addresses == {"server": "10.8.0.1", "nats-1": "10.8.0.253",
                         "nats-2": "10.8.0.252", "nats-3": "10.8.0.251"}
    assert doc["networks"]["fleet"]["ipam"]["config"][0]["gateway"] == "10.8.0.254"


def test_files_carry_each_replicas_own_nats_user_and_only_hashes(fleet: Path) -> None:
    p = plan(fleet, wireguard="off", sim=True)
    compose.write_files(p)
    out = p.compose_dir
    passwords = {}
    for i, name in enumerate(replicas.replica_names(3)):
        secret = out / "secrets" / name / replicas.PASSWORD_FILE
        assert stat.S_IMODE(secret.stat().st_mode) == 0o600
        assert stat.S_IMODE((out / "secrets" / name / "tls.key").stat().st_mode) == 0o600
        passwords[name] = secret.read_text().strip()
        assert len(passwords[name]) >= 40
        cfg = yaml.safe_load((out / "server" / f"{name}.yaml").read_text())
        assert (cfg["listen_port"], cfg["web"]["listen_port"]) == (8080 + i, 8443 + i)
        assert cfg["web"]["replica_ports"] == [8443, 8444, 8445]  # the page's failover
        assert cfg["cluster"]["credentials"] == {
            "user": name, "password_file": f"{SECRETS_RUN}/{replicas.PASSWORD_FILE}"}
        assert cfg["cluster"]["nats_urls"][0] == f"nats://{replicas.NATS_NODES[i]}:4222"
        assert cfg["cluster"]["state_replicas"] == 3
        # The section parses as the server will parse it (the password file in its place).
        cfg["cluster"]["credentials"]["password_file"] = str(secret)
        assert parse_cluster(cfg["cluster"], out, out / "relay.yaml") is not None
    assert len(set(passwords.values())) == 3
    for node in replicas.NATS_NODES:
        conf_path = out / "nats" / node / replicas.NATS_CONF
        assert stat.S_IMODE(conf_path.stat().st_mode) == 0o600
        text = conf_path.read_text()
        conf = json.loads(text)  # JSON: the NATS config format reads it
        users = {u["user"]: u for u in conf["authorization"]["users"]}
        assert set(users) == set(passwords)
        for name, user in users.items():
            assert passwords[name] not in text
            assert bcrypt.checkpw(passwords[name].encode(), user["password"].encode())
            assert user["permissions"] == replicas.nats_permissions()
        assert conf["server_name"] == node and node not in "".join(conf["cluster"]["routes"])
    client = yaml.safe_load((out / "robots" / "husky1" / "client.yaml").read_text())
    assert client["server_url"] == [f"ws://10.8.0.1:{8080 + i}/" for i in range(3)]
    # The next `up` keeps the passwords (the NATS volumes and running replicas agree).
    compose.write_files(p)
    assert {n: (out / "secrets" / n / replicas.PASSWORD_FILE).read_text().strip()
            for n in passwords} == passwords


def test_a_password_file_planted_as_a_link_is_refused(fleet: Path, tmp_path: Path) -> None:
    p = plan(fleet, wireguard="off")
    target = tmp_path / "elsewhere"
    target.write_text("x\n")
    link = p.compose_dir / "secrets" / "relay-1" / replicas.PASSWORD_FILE
    link.parent.mkdir(parents=True)
    link.symlink_to(target)
    with pytest.raises(ConfigError, match=r"relay-1/nats\.password"):
        compose.write_files(p)
    assert target.read_text() == "x\n"


def test_page_urls_of_every_replica(fleet: Path) -> None:
    assert composereplicas.page_urls(plan(fleet, wireguard="off", bind="::1",
                                          https_port=9443)) == [
        "https://[::1]:9443/", "https://[::1]:9444/", "https://[::1]:9445/"]
    assert composereplicas.page_urls(plan(fleet, wireguard="off")) == [
        "https://fleet.example:8443/", "https://fleet.example:8444/",
        "https://fleet.example:8445/"]  # the endpoint's host


def test_one_replica_is_todays_single_server(fleet: Path) -> None:
    doc = compose.render(plan(fleet, wireguard="off", replicas=1))
    assert set(doc["services"]) == {"server"} and set(doc["volumes"]) == {"server-data"}


@pytest.mark.parametrize("count", [0, 9, -1])
def test_replica_counts_out_of_range_are_refused(fleet: Path, count: int) -> None:
    with pytest.raises(ConfigError, match="--replicas"):
        composerun.default_options(fleet, replicas=count)


def test_the_cli_names_the_option(fleet: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["up", "--replicas", "9", "--fleet", str(fleet)])
    assert code != 0
    assert "--replicas" in capsys.readouterr().err


def test_permissions_allow_the_fleets_subjects_and_buckets_only() -> None:
    perms = replicas.nats_permissions("fleetctl")
    publish = perms["publish"]["allow"]
    assert "fleetctl.>" in publish and "$KV.fleetctl_robots.>" in publish
    assert "$KV.fleetctl_latched.>" in publish
    assert not any(s in publish for s in (">", "$JS.API.>", "$KV.>", "_INBOX.>"))
    assert perms["subscribe"]["allow"] == ["fleetctl.>", "_INBOX.>"]
