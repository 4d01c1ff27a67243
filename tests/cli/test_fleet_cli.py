"""The fleet commands end to end through the real CLI entry point (``main``)."""

from __future__ import annotations

import hashlib
import json
import os
import re
import stat
from collections.abc import Callable, Collection
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from fleetctl.cli.main import build_app, main
from fleetctl.errors import ExitCode


class Cli:
    def __init__(self, capsys: pytest.CaptureFixture[str], fleet: Path) -> None:
        self.capsys, self.fleet = capsys, fleet

    def __call__(self, *args: str, code: int = 0) -> tuple[str, str]:
        rc = main([*args])
        out, err = self.capsys.readouterr()
        assert rc == code, f"exit {rc} != {code}\nstdout: {out}\nstderr: {err}"
        return out, err


@pytest.fixture
def synced(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    """Replace the running-deployment sync by a recorder (no Docker here)."""
    from fleetctl.deploy import live

    calls: list[Path] = []

    def fake(fleet_dir: Path, progress: Callable[[str], None],
             changed: Collection[Path] | None = None) -> str | None:
        calls.append(fleet_dir)
        progress("checking")
        return None

    monkeypatch.setattr(live, "sync_running", fake)
    return calls


@pytest.fixture
def cli(capsys: pytest.CaptureFixture[str], tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch, synced: list[Path]) -> Cli:
    fleet = tmp_path / "fleet"
    monkeypatch.setenv("FLEET_DIR", str(fleet))
    return Cli(capsys, fleet)


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


@pytest.fixture
def fleet(cli: Cli) -> Path:
    cli("init", "--endpoint", "vpn.example.com:51820")
    cli("add-robot", "husky1")
    return cli.fleet


def test_help_lists_every_command() -> None:
    out = CliRunner().invoke(build_app(), ["--help"]).output
    for cmd in ("init", "set-endpoint", "add-robot", "remove-robot", "add-user", "set-user",
                "remove-user", "list", "render", "export"):
        assert cmd in out


def test_init_creates_fleet_and_refuses_overwrite(cli: Cli, tmp_path: Path) -> None:
    out, _ = cli("init", str(tmp_path / "f2"), "--endpoint", "1.2.3.4:51820",
                 "--subnet", "127.0.1.0/24", "--server-ip", "127.0.1.1")
    assert "server public key:" in out
    doc = yaml.safe_load((tmp_path / "f2/fleet.yaml").read_text())
    assert doc["subnet"] == "127.0.1.0/24" and doc["server_ip"] == "127.0.1.1"
    before = _snapshot(tmp_path / "f2")
    _, err = cli("init", str(tmp_path / "f2"), "--endpoint", "x:1", code=ExitCode.CONFLICT)
    assert "already exists" in err and "--force" in err
    assert _snapshot(tmp_path / "f2") == before
    cli("init", str(tmp_path / "f2"), "--endpoint", "x:1", "--force")
    assert _snapshot(tmp_path / "f2")["keys/server.key"] != before["keys/server.key"]


def test_init_bad_subnet(cli: Cli) -> None:
    _, err = cli("init", "--endpoint", "h:1", "--subnet", "10.8.0.0/33", code=ExitCode.CONFIG)
    assert "subnet" in err
    assert not cli.fleet.exists()


def test_add_robot_allocates_and_writes(fleet: Path, cli: Cli) -> None:
    out, _ = cli("add-robot", "jackal2", "--mtu", "1380", "--output", "json")
    result = json.loads(out)
    assert result["robot"]["ip"] == "10.8.0.3"
    assert "PrivateKey" not in out and "private_key" not in out
    conf = (fleet / "robots/jackal2/wireguard/wg0.conf").read_text()
    assert "MTU = 1380" in conf and "Address = 10.8.0.3/32" in conf
    assert "AllowedIPs = 10.8.0.3/32" in (fleet / "server/wireguard/wg0.conf").read_text()


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["husky1"], ExitCode.CONFLICT, "duplicate robot name 'husky1'"),
        (["other", "--ip", "10.8.0.2"], ExitCode.CONFLICT,
         "robot 'other': ip (--ip): 10.8.0.2 is already used by robot 'husky1'"),
        (["other", "--ip", "10.9.0.2"], ExitCode.CONFIG,
         "robot 'other': ip (--ip): 10.9.0.2 is outside the fleet subnet"),
        (["other", "--ip", "10.8.0.1"], ExitCode.CONFLICT, "ip (--ip): 10.8.0.1 is the server's"),
        (["other", "--ip", "10.8.0.255"], ExitCode.CONFIG, "ip (--ip): 10.8.0.255 is the netw"),
        (["other", "--ip", "banana"], ExitCode.CONFIG,
         "robot 'other': ip (--ip): not an IPv4 address: 'banana'"),
        # An empty value used to mean "the next free address".
        (["other", "--ip", ""], ExitCode.CONFIG, "ip (--ip): not an IPv4 address: ''"),
        (["bad-name"], ExitCode.CONFIG, "not a ROS namespace segment"),
        (["9lives"], ExitCode.CONFIG, "not a ROS namespace segment"),
        (["a__b"], ExitCode.CONFIG, "not a ROS namespace segment"),
        # `fleetctl replay` sends a recorded husky1 as husky1_replay (status and the page
        # mark such a name as a replay).
        (["dock_replay"], ExitCode.CONFIG, "robot name 'dock_replay' ends in _replay, which "
         "`fleetctl replay` gives replayed robots (husky1 -> husky1_replay): choose another"),
        # Out of range is a usage error, above 65535 as below 576 (once 2 and 3).
        (["other", "--mtu", "100"], ExitCode.USAGE, "Invalid value for '--mtu': 100 is not in "
         "576..9000"),
        (["other", "--mtu", "575"], ExitCode.USAGE, "575 is not in 576..9000"),
        (["other", "--mtu", "9001"], ExitCode.USAGE, "9001 is not in 576..9000"),
        (["other", "--mtu", "99999"], ExitCode.USAGE, "99999 is not in 576..9000"),
        (["r" * 300], ExitCode.CONFIG, "is 300 characters long (at most 63)"),
        (["r\u00e9"], ExitCode.CONFIG, "not a ROS namespace segment"),
        (["other", "--mtu", "\uff11\uff12\uff18\uff10"], ExitCode.USAGE, "ASCII digits"),
        (["other", "--ip", "\uff11\uff10.8.0.9"], ExitCode.CONFIG, "not an IPv4 address"),
    ],
)
def test_add_robot_errors_change_nothing(fleet: Path, cli: Cli, args: list[str], code: int,
                                         message: str) -> None:
    before = _snapshot(fleet)
    _, err = cli("add-robot", *args, code=code)
    assert message in err
    assert "Traceback" not in err
    assert _snapshot(fleet) == before


def test_full_subnet(cli: Cli) -> None:
    cli("init", "--endpoint", "h:51820", "--subnet", "10.9.0.0/30")
    cli("add-robot", "r1")
    before = _snapshot(cli.fleet)
    _, err = cli("add-robot", "r2", code=ExitCode.CONFLICT)
    assert "10.9.0.0/30 is full" in err
    assert _snapshot(cli.fleet) == before


def test_remove_robot(fleet: Path, cli: Cli) -> None:
    cli("remove-robot", "husky1")
    assert not (fleet / "robots/husky1").exists()
    assert not (fleet / "keys/robots/husky1.key").exists()
    assert "[Peer]" not in (fleet / "server/wireguard/wg0.conf").read_text()
    assert "husky1" not in (fleet / "server/auth.yaml").read_text()
    _, err = cli("remove-robot", "husky1", code=ExitCode.CONFIG)
    assert "robot 'husky1' is not in" in err


@pytest.mark.parametrize(("change", "named"), [
    (lambda d: (d / "notes.txt").write_text("calibration of arm 2\n"), "notes.txt"),
    (lambda d: (d / "client.yaml").write_text(
        (d / "client.yaml").read_text() + "# tuned on site\n"), "client.yaml"),
    (lambda d: (d / "wireguard" / "backup.conf").symlink_to("/etc/hostname"),
     "wireguard/backup.conf"),
])
def test_remove_robot_keeps_what_an_operator_put_in_its_directory(
        fleet: Path, cli: Cli, change: Callable[[Path], object], named: str) -> None:
    """The robot's directory goes as a whole: someone's files in it stop the removal."""
    change(fleet / "robots/husky1")
    before = _snapshot(fleet)
    _, err = cli("remove-robot", "husky1", code=ExitCode.CONFLICT)
    assert "robots/husky1 holds files fleetctl did not write" in err and named in err
    assert "--force" in err
    assert _snapshot(fleet) == before
    cli("remove-robot", "husky1", "--force")
    assert not (fleet / "robots/husky1").exists()
    assert "husky1" not in (fleet / "server/auth.yaml").read_text()


def test_add_user_prints_token_once_and_stores_hash(fleet: Path, cli: Cli) -> None:
    out, _ = cli("add-user", "alice@example.com", "--role", "operator", "--output", "json")
    token = json.loads(out)["token"]
    stored = yaml.safe_load((fleet / "fleet.yaml").read_text())["users"][0]
    assert stored["token_sha256"] == hashlib.sha256(token.encode()).hexdigest()
    assert token not in (fleet / "fleet.yaml").read_text()
    assert token not in (fleet / "server/auth.yaml").read_text()
    list_out, _ = cli("list")
    assert token not in list_out and "alice@example.com" in list_out


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["bob@example.com", "--role", "pilot"], ExitCode.USAGE, "unknown role 'pilot'"),
        (["not-an-email", "--role", "viewer"], ExitCode.CONFIG, "not an email address"),
    ],
)
def test_add_user_errors(fleet: Path, cli: Cli, args: list[str], code: int,
                         message: str) -> None:
    before = _snapshot(fleet)
    _, err = cli("add-user", *args, code=code)
    assert message in err
    assert _snapshot(fleet) == before


def test_duplicate_and_remove_user(fleet: Path, cli: Cli) -> None:
    cli("add-user", "bob@example.com", "--role", "viewer")
    before = _snapshot(fleet)
    _, err = cli("add-user", "bob@example.com", "--role", "admin", code=ExitCode.CONFLICT)
    # What an operator then wants is a new token for someone who lost theirs: say how.
    assert err == (f"fleetctl: error: user 'bob@example.com' is already in {fleet}/fleet.yaml "
                   "(viewer): to give them a new token, `fleetctl remove-user "
                   "bob@example.com` (their old token stops working) and add them again\n")
    assert _snapshot(fleet) == before
    cli("remove-user", "bob@example.com")
    assert "bob@example.com" not in (fleet / "server/auth.yaml").read_text()
    _, err = cli("remove-user", "bob@example.com", code=ExitCode.CONFIG)
    assert "is not in" in err


def test_names_that_differ_only_in_case_are_duplicates(fleet: Path, cli: Cli) -> None:
    """Bob@Example.com beside bob@example.com was a second user (one person, two tokens;
    remove-user of one spelling left the other working), and robot Husky1 beside husky1
    had key files that are one file on a case-insensitive file system."""
    cli("add-user", "bob@example.com", "--role", "viewer")
    before = _snapshot(fleet)
    _, err = cli("add-user", "Bob@Example.COM", "--role", "admin", code=ExitCode.CONFLICT)
    assert err == ("fleetctl: error: user 'Bob@Example.COM': email: user 'Bob@Example.COM' "
                   "differs from user 'bob@example.com' only in case\n")
    _, err = cli("add-robot", "Husky1", code=ExitCode.CONFLICT)
    assert err == ("fleetctl: error: robot 'Husky1': name: robot name 'Husky1' differs from "
                   "robot 'husky1' only in case: their files would be the same on a "
                   "case-insensitive file system\n")
    _, err = cli("remove-user", "BOB@example.com", code=ExitCode.CONFIG)
    assert err.endswith("fleet.yaml (there is 'bob@example.com')\n")
    assert _snapshot(fleet) == before
    # The same in a fleet.yaml edited by hand.
    text = (fleet / "fleet.yaml").read_text()
    (fleet / "fleet.yaml").write_text(text.replace("users:\n", "users:\n- email: BOB@example.com"
                                                   "\n  role: viewer\n  token_sha256: "
                                                   + "ab" * 32 + "\n"))
    _, err = cli("render", code=ExitCode.CONFIG)  # as every problem of a hand-edited file
    assert "users[1].email: user 'bob@example.com' differs from user 'BOB@example.com'" in err


def test_fleet_yaml_keeps_the_mode_its_owner_gave_it(fleet: Path, cli: Cli) -> None:
    """A fleet.yaml made 0600 by its owner came back 0644 (readable by all) from the next
    command that wrote it; a group- or world-writable one stays so no longer."""
    path = fleet / "fleet.yaml"
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    for given, kept in ((0o600, 0o600), (0o640, 0o640), (0o666, 0o644), (0o775, 0o644)):
        path.chmod(given)
        cli("add-user", f"u{given:o}@example.com", "--role", "viewer")
        assert stat.S_IMODE(path.stat().st_mode) == kept, oct(given)


def test_list_json(fleet: Path, cli: Cli) -> None:
    cli("add-user", "v@example.com", "--role", "viewer")
    out, _ = cli("list", "--output", "json")
    info = json.loads(out)
    assert [r["name"] for r in info["fleet"]["robots"]] == ["husky1"]
    assert info["fleet"]["users"][0]["role"] == "viewer"
    assert set(info["robot_public_keys"]) == {"husky1"}
    assert "PrivateKey" not in out


def test_render_idempotent_and_dry_run(fleet: Path, cli: Cli) -> None:
    out, _ = cli("render")
    assert "already up to date" in out and "create" not in out and "update" not in out
    (fleet / "server/auth.yaml").unlink()
    before = _snapshot(fleet)
    out, _ = cli("render", "--dry-run")
    assert "would create server/auth.yaml" in out
    assert _snapshot(fleet) == before
    cli("add-robot", "r2", "--dry-run")
    assert _snapshot(fleet) == before


def test_export(fleet: Path, cli: Cli, tmp_path: Path) -> None:
    out, _ = cli("export", "husky1", "--out", str(tmp_path / "bundle"))
    assert (tmp_path / "bundle/wg0.conf").exists() and "bundle" in out
    cli("export", "husky1", "--out", str(tmp_path / "husky1.tar.gz"))
    assert (tmp_path / "husky1.tar.gz").stat().st_size > 0
    _, err = cli("export", "nobody", code=ExitCode.CONFIG)
    assert "robot 'nobody' is not in" in err


def test_malformed_fleet_yaml_names_file_line_field(fleet: Path, cli: Cli) -> None:
    path = fleet / "fleet.yaml"
    path.write_text(path.read_text().replace("ip: 10.8.0.2", "ip: 10.8.0.999"))
    _, err = cli("list", code=ExitCode.CONFIG)
    assert f"{path}:" in err and "robots[0].ip: not an IPv4 address" in err
    line = int(err.split(f"{path}:")[1].split(":")[0])
    assert "10.8.0.999" in path.read_text().splitlines()[line - 1]


def test_missing_fleet_directory(cli: Cli, tmp_path: Path) -> None:
    for cmd in (["list"], ["render"], ["add-robot", "x"], ["add-user", "a@b.c", "--role",
                                                            "viewer"]):
        _, err = cli(*cmd, "--fleet", str(tmp_path / "missing"), code=ExitCode.CONFIG)
        assert "does not exist" in err


def test_keys_never_in_output(fleet: Path, cli: Cli) -> None:
    secrets = [(fleet / p).read_text().strip() for p in
               ("keys/server.key", "keys/robots/husky1.key", "keys/robots/husky1.psk")]
    outputs = [cli("list")[0], cli("list", "-o", "json")[0], cli("render", "-o", "json")[0],
               cli("add-robot", "r3", "-o", "json")[0], cli("add-robot", "r4")[0]]
    for out in outputs:
        for secret in secrets:
            assert secret not in out


def test_init_without_arguments_then_set_endpoint(cli: Cli, synced: list[Path]) -> None:
    cli.fleet.mkdir()
    out, err = cli("init")
    assert "endpoint not set" in out and "HTTPS port 8443" in out and not err
    assert yaml.safe_load((cli.fleet / "fleet.yaml").read_text())["endpoint"] is None
    out, err = cli("add-robot", "husky1")
    warnings = [line for line in err.splitlines() if "warning" in line]
    assert warnings == [
        f"fleetctl: warning: {cli.fleet / 'fleet.yaml'} has no endpoint, so the robots' "
        "wg0.conf have no Endpoint and cannot reach the server: run "
        "`fleetctl set-endpoint HOST:PORT`"]
    conf = cli.fleet / "robots/husky1/wireguard/wg0.conf"
    assert "\nEndpoint" not in conf.read_text()
    assert (cli.fleet / "robots/husky1/client.yaml").exists()
    assert "husky1" in (cli.fleet / "server/auth.yaml").read_text()
    out, _ = cli("set-endpoint", "vpn.example.com:51820")
    assert "endpoint vpn.example.com:51820 (was not set)" in out
    assert "certificate made again" in out
    assert "\nEndpoint = vpn.example.com:51820\n" in conf.read_text()
    assert yaml.safe_load((cli.fleet / "fleet.yaml").read_text())["endpoint"] == (
        "vpn.example.com:51820")
    assert synced == [cli.fleet, cli.fleet]  # add-robot, set-endpoint (not init)
    _, err = cli("render")
    assert "warning" not in err


def test_set_endpoint_on_another_port_warns_about_wireguard_port(fleet: Path, cli: Cli) -> None:
    """The server keeps listening on wireguard_port: right behind port forwarding, a dead
    tunnel otherwise, so the operator is told which of the two they have to mean."""
    out, err = cli("set-endpoint", "vpn.example.com:443")
    assert "endpoint vpn.example.com:443" in out
    assert ("fleetctl: warning: the endpoint's port 443 is not wireguard_port 51820"
            in err) and "set wireguard_port: 443 in" in err
    _, err = cli("set-endpoint", "vpn.example.com:51820")
    assert "warning" not in err


@pytest.mark.parametrize("endpoint", ["vpn.example.com", "vpn:0", "a b:1", "h:99999",
                                      "x\n[Peer]:1", "host:01", "h:051820", "h:00"])
def test_set_endpoint_bad_input_changes_nothing(fleet: Path, cli: Cli, endpoint: str,
                                                synced: list[Path]) -> None:
    before = _snapshot(fleet)
    calls = len(synced)
    _, err = cli("set-endpoint", endpoint, code=ExitCode.CONFIG)
    assert err.startswith("fleetctl: error: endpoint: expected HOST:PORT")
    assert len(err.strip().splitlines()) == 1
    assert _snapshot(fleet) == before and len(synced) == calls


def test_change_commands_sync_a_running_fleet(fleet: Path, cli: Cli,
                                              synced: list[Path]) -> None:
    synced.clear()
    cli("add-user", "a@example.com", "--role", "viewer")
    cli("remove-user", "a@example.com")
    cli("add-robot", "r2", "--dry-run")  # a dry run changes nothing: no sync
    cli("render", "-o", "json")
    cli("remove-robot", "husky1")
    cli("list")
    assert synced == [fleet] * 4


def test_sync_note_is_printed(fleet: Path, cli: Cli, monkeypatch: pytest.MonkeyPatch) -> None:
    from fleetctl.deploy import live

    monkeypatch.setattr(live, "sync_running", lambda d, p, changed: "running fleet: peers synced")
    out, _ = cli("render")
    assert out.rstrip().endswith("running fleet: peers synced")
    out, err = cli("render", "-o", "json")
    json.loads(out)  # stdout stays one JSON document
    assert "running fleet: peers synced" in err


def test_render_force_after_hand_edit(fleet: Path, cli: Cli) -> None:
    client = fleet / "robots/husky1/client.yaml"
    client.write_text(client.read_text() + "# my change\n")
    before = _snapshot(fleet)
    _, err = cli("render", code=ExitCode.CONFIG)
    assert err == (f"fleetctl: error: {client} was edited by hand: put topics in fleet.yaml "
                   "robots[0].publish / subscribe / battery_topic, then run "
                   "`fleetctl render --force` to overwrite\n")
    assert _snapshot(fleet) == before
    cli("render", "--force")
    assert "# my change" not in client.read_text()


# --- issue 14: names, Unicode digits, one-line errors, round trips ----------------------


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["--name", "x\n[Interface]\nPostUp = touch /tmp/PWNED #"], ExitCode.CONFIG,
         "name (--name): fleet name 'x\\n[Interface]\\nPostUp = touch /tmp/PWNED "),
        (["--name", "my fleet"], ExitCode.CONFIG, "name (--name): fleet name 'my fleet' must"),
        (["--name", "f" * 64], ExitCode.CONFIG, "is 64 characters long (at most 63)"),
        (["--endpoint", "h:\u00b2"], ExitCode.CONFIG, "endpoint (--endpoint): expected HOST:PORT"),
        (["--endpoint", "h:\uff15\uff11\uff18\uff12\uff10"], ExitCode.CONFIG,
         "endpoint (--endpoint): expected HOST:PORT"),
        (["--subnet", "10.9.0.0/32"], ExitCode.CONFIG, "subnet (--subnet): 10.9.0.0/32 is too "),
        (["--subnet", "10.9.0.0/\uff12\uff14"], ExitCode.CONFIG, "subnet (--subnet): not a "),
        (["--https-port", "\uff18\uff14\uff14\uff13"], ExitCode.USAGE,
         "Invalid value for '--https-port'"),
    ],
)
def test_init_errors_are_one_line_and_change_nothing(cli: Cli, tmp_path: Path,
                                                     args: list[str], code: int,
                                                     message: str) -> None:
    target = tmp_path / "new"
    _, err = cli("init", str(target), *args, code=code)
    assert message in err and "Traceback" not in err
    if code != ExitCode.USAGE:  # click draws its own box around usage errors
        assert err.startswith("fleetctl: error: ") and len(err.strip().splitlines()) == 1
    assert not target.exists()


def test_init_default_name_from_a_directory_name(cli: Cli, tmp_path: Path) -> None:
    cli("init", str(tmp_path / "My Fleet (2)"))
    doc = yaml.safe_load((tmp_path / "My Fleet (2)" / "fleet.yaml").read_text())
    assert doc["name"] == "My-Fleet-2"


def test_hand_edited_hostile_name_is_refused_by_render(fleet: Path, cli: Cli) -> None:
    path = fleet / "fleet.yaml"
    doc = yaml.safe_load(path.read_text())
    doc["name"] = "x\n[Interface]\nPostUp = touch /tmp/PWNED #"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    before = _snapshot(fleet)
    _, err = cli("render", code=ExitCode.CONFIG)
    assert f"{path}:" in err and ": name: fleet name" in err
    assert len(err.strip().splitlines()) == 1 and _snapshot(fleet) == before


@pytest.mark.parametrize("email", ["a\U0001f916@example.com", "\U0001d4b6@\u4f8b\u3048.jp",
                                   "\U00020000x@example.org"])
def test_astral_email_round_trips(fleet: Path, cli: Cli, email: str) -> None:
    cli("add-user", email, "--role", "viewer")
    auth = yaml.safe_load((fleet / "server/auth.yaml").read_text())
    assert email in [i["name"] for i in auth["identities"]]
    raw = (fleet / "server/auth.yaml").read_bytes()
    assert raw.isascii() and b"\\ud8" not in raw.lower()  # \U escapes, never surrogates
    assert [u["email"] for u in yaml.safe_load((fleet / "fleet.yaml").read_text())["users"]] \
        == [email]
    out, _ = cli("list", "-o", "json")
    assert email in [u["email"] for u in json.loads(out)["fleet"]["users"]]
    cli("remove-user", email)


@pytest.mark.parametrize(("email", "message"), [
    ("a" * 250 + "@x.org", "characters long (at most 254)"),
    ("a b@x.org", "is not an email address"),
    ("a\u2028b@x.org", "is not an email address"),
    ("a@b@c", "is not an email address"),
])
def test_bad_email_is_refused(fleet: Path, cli: Cli, email: str, message: str) -> None:
    before = _snapshot(fleet)
    _, err = cli("add-user", email, "--role", "viewer", code=ExitCode.CONFIG)
    assert message in err and len(err.strip().splitlines()) == 1
    assert _snapshot(fleet) == before


def test_export_out_errors(fleet: Path, cli: Cli, tmp_path: Path,
                           monkeypatch: pytest.MonkeyPatch) -> None:
    import functools

    from fleetctl.cli import fleet as fleet_cli
    from fleetctl.deploy.export import export_robot
    from tests.deploy.test_bundle import fake_wheel

    monkeypatch.setattr(fleet_cli, "export_robot",
                        functools.partial(export_robot, wheel=fake_wheel(tmp_path)))
    (tmp_path / "afile").write_text("mine\n")
    _, err = cli("export", "husky1", "--out", str(tmp_path / "afile"), code=ExitCode.CONFLICT)
    assert "--out" in err and "exists and is not a directory" in err
    _, err = cli("export", "husky1", "--out", "/proc/fleetctl-nope/b", code=ExitCode.CONFIG)
    assert err == ("fleetctl: error: --out /proc/fleetctl-nope/b: directory /proc/fleetctl-nope "
                   "does not exist\n")
    _, err = cli("export", "husky1", "--out", "/proc/fleetctl-nope.tgz",
                 code=ExitCode.ENVIRONMENT)
    assert err.startswith("fleetctl: error: --out /proc/fleetctl-nope.tgz: ")
    assert len(err.strip().splitlines()) == 1
    cli("export", "husky1", "--out", str(tmp_path / "b.tgz"))
    assert (tmp_path / "b.tgz").is_file()


def test_concurrent_changes_are_not_lost(tmp_path: Path) -> None:
    """Each change reads fleet.yaml and writes it back: without the fleet lock, commands run
    at once all reported success and only the last write survived."""
    import subprocess
    import sys

    fleet = tmp_path / "f"
    assert main(["init", str(fleet), "--endpoint", "vpn.example.org:51820"]) == 0
    procs = [subprocess.Popen([sys.executable, "-m", "fleetctl.cli.main", "add-robot", f"r{i}",
                               "--fleet", str(fleet)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True) for i in range(4)]
    procs.append(subprocess.Popen([sys.executable, "-m", "fleetctl.cli.main", "add-user",
                                   "a@example.org", "--role", "viewer", "--fleet", str(fleet)],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
    for proc in procs:
        _out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
    data = yaml.safe_load((fleet / "fleet.yaml").read_text())
    assert sorted(r["name"] for r in data["robots"]) == ["r0", "r1", "r2", "r3"]
    assert len({r["ip"] for r in data["robots"]}) == 4
    assert [u["email"] for u in data["users"]] == ["a@example.org"]
    peers = (fleet / "server" / "wireguard" / "wg0.conf").read_text().count("[Peer]")
    assert peers == 4


@pytest.mark.parametrize("victim", ["fleet.yaml", "keys/server.key"])
@pytest.mark.parametrize("make", ["link to /dev/zero", "fifo"])
def test_a_fleet_file_that_is_a_device_or_fifo_is_a_config_error(
        fleet: Path, cli: Cli, victim: str, make: str) -> None:
    """Read unbounded, /dev/zero ran the command out of memory and a FIFO hung it."""
    path = fleet / victim
    path.unlink()
    if make == "fifo":
        os.mkfifo(path)
    else:
        path.symlink_to("/dev/zero")
    _, err = cli("render", code=ExitCode.CONFIG)
    assert f"{victim}: cannot read" in err and "not a regular file" in err


# --- the fleet lock: never made outside a fleet, not needed by a dry run -----------------


_CHANGE_COMMANDS = [["add-robot", "r1"], ["remove-robot", "r1"], ["render"],
                    ["add-user", "a@example.com", "--role", "viewer"],
                    ["remove-user", "a@example.com"], ["set-endpoint", "h.example:51820"]]


@pytest.mark.parametrize("dry_run", [[], ["--dry-run"]])
@pytest.mark.parametrize("args", _CHANGE_COMMANDS)
def test_a_change_outside_a_fleet_leaves_no_lock_file(cli: Cli, args: list[str],
                                                      dry_run: list[str]) -> None:
    """A directory without fleet.yaml is not a fleet: the command fails and changes
    nothing (it used to leave .fleetctl.lock behind)."""
    cli.fleet.mkdir()
    _, err = cli(*args, *dry_run, code=ExitCode.CONFIG)
    assert "is not a fleet directory" in err
    assert list(cli.fleet.iterdir()) == []


@pytest.fixture
def lock_refused(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Opening FLEET/.fleetctl.lock fails as in a read-only fleet directory (the tests may
    run as root, whom a mode of 0555 does not stop). Returns the flags of each attempt."""
    from fleetctl.deploy.operations import LOCK_FILE

    real_open = os.open
    attempts: list[int] = []

    def fake_open(path: str | os.PathLike[str], flags: int, *args: int, **kwargs: object) -> int:
        if os.path.basename(os.fspath(path)) == LOCK_FILE:
            attempts.append(flags)
            raise PermissionError(1, "Operation not permitted", os.fspath(path))
        return real_open(path, flags, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(os, "open", fake_open)
    return attempts


def test_a_dry_run_in_a_read_only_fleet_works(fleet: Path, cli: Cli,
                                              lock_refused: list[int]) -> None:
    (fleet / ".fleetctl.lock").unlink()
    (fleet / "server/auth.yaml").unlink()
    before = _snapshot(fleet)
    out, _ = cli("render", "--dry-run")
    assert "would create server/auth.yaml" in out
    cli("add-robot", "r2", "--dry-run")
    assert _snapshot(fleet) == before and not (fleet / ".fleetctl.lock").exists()
    assert lock_refused and not any(flags & os.O_CREAT for flags in lock_refused)


def test_a_lock_file_that_cannot_be_made_is_a_write_error(fleet: Path, cli: Cli,
                                                          lock_refused: list[int]) -> None:
    """exit 5 (a file could not be written), not 3 (a bad config)."""
    (fleet / ".fleetctl.lock").unlink()
    before = _snapshot(fleet)
    _, err = cli("render", code=ExitCode.ENVIRONMENT)
    assert err.startswith(f"fleetctl: error: {fleet / '.fleetctl.lock'}: cannot write: "
                          "Operation not permitted; nothing was changed")
    assert len(err.strip().splitlines()) == 1 and _snapshot(fleet) == before


def test_a_dry_run_does_not_make_the_lock_file(cli: Cli) -> None:
    cli("init")
    for args in _CHANGE_COMMANDS[:1] + _CHANGE_COMMANDS[2:4] + _CHANGE_COMMANDS[5:]:
        cli(*args, "--dry-run")
    assert not (cli.fleet / ".fleetctl.lock").exists()
    cli("add-robot", "r1")
    assert (cli.fleet / ".fleetctl.lock").exists()
    cli("remove-robot", "r1", "--dry-run")  # a shared lock on the existing file


def test_a_fleet_directory_that_is_a_file(cli: Cli, tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """It used to be reported as missing."""
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    monkeypatch.setenv("FLEET_DIR", str(afile))
    for cmd in (["list"], ["render", "--dry-run"], ["add-robot", "x"]):
        _, err = cli(*cmd, code=ExitCode.CONFIG)
        assert f"fleet directory {afile} exists and is not a directory" in err
    assert afile.read_text() == "mine\n"


def test_mtu_help_states_its_range() -> None:
    out = CliRunner().invoke(build_app(), ["add-robot", "--help"], terminal_width=200).output
    assert "576..9000" in out


def test_dry_runs_say_what_would_be_done(fleet: Path, cli: Cli) -> None:
    """`dry run: removed robot 'husky1'` read as done."""
    cli("add-user", "a@example.com", "--role", "viewer")
    before = _snapshot(fleet)
    firsts = {args[0]: cli(*args, "--dry-run")[0].splitlines()[0] for args in (
        ["remove-robot", "husky1"], ["add-robot", "r2"], ["remove-user", "a@example.com"],
        ["add-user", "b@example.com", "--role", "admin"], ["render"],
        ["set-endpoint", "other.example.com:51820"])}
    assert firsts == {
        "remove-robot": "dry run: would remove robot 'husky1'",
        "add-robot": "dry run: would add robot 'r2' at 10.8.0.3",
        "remove-user": "dry run: would remove user 'a@example.com'",
        "add-user": "dry run: would add user 'b@example.com' (admin)",
        "render": f"dry run: would render {fleet}",
        "set-endpoint": "dry run: would set endpoint other.example.com:51820 (was "
                        "vpn.example.com:51820)"}
    out, _ = cli("set-endpoint", "other.example.com:51820", "--dry-run")
    assert "certificate would be made again" in out
    out, _ = cli("add-robot", "r2", "--dry-run")
    assert "public key" not in out and "next:" not in out  # a key pair that is not kept
    out, _ = cli("init", str(fleet.parent / "new"), "--dry-run")
    assert out.startswith("dry run: would create fleet 'new': subnet")
    assert _snapshot(fleet) == before and not (fleet.parent / "new").exists()
    out, _ = cli("remove-robot", "husky1")
    assert out.startswith("removed robot 'husky1'\n")


def test_export_lists_the_tarball_by_its_name(fleet: Path, cli: Cli, tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """It was listed as `create .` (relative to itself)."""
    import functools

    from fleetctl.cli import fleet as fleet_cli
    from fleetctl.deploy.export import export_robot
    from tests.deploy.test_bundle import fake_wheel

    monkeypatch.setattr(fleet_cli, "export_robot",
                        functools.partial(export_robot, wheel=fake_wheel(tmp_path)))
    monkeypatch.chdir(tmp_path)
    out, _ = cli("export", "husky1", "--out", "b.tgz", "--dry-run")
    assert out.splitlines() == ["dry run: would write the bundle of 'husky1': b.tgz",
                                "  would create b.tgz"]
    (tmp_path / "sub").mkdir()
    out, _ = cli("export", "husky1", "--out", str(tmp_path / "sub" / "b.tar.gz"))
    assert out.splitlines()[1:] == ["  create b.tar.gz"]
    out, _ = cli("export", "husky1", "--out", "bundle")
    assert "  create wg0.conf" in out.splitlines()


@pytest.mark.parametrize("args", [["list"], ["render"], ["add-robot", "r2"]])
def test_a_fleet_yaml_linked_to_nothing_is_named_a_dangling_link(cli: Cli,
                                                                 args: list[str]) -> None:
    """It was 'not found: FLEET is not a fleet directory' though fleet.yaml is right there."""
    cli.fleet.mkdir()
    (cli.fleet / "fleet.yaml").symlink_to(cli.fleet.parent / "gone.yaml")
    _, err = cli(*args, code=ExitCode.CONFIG)
    assert err == (f"fleetctl: error: {cli.fleet / 'fleet.yaml'}: is a symbolic link to "
                   f"{cli.fleet.parent / 'gone.yaml'}, which does not exist\n")


@pytest.mark.parametrize("args", [["status"], ["logs"], ["down"]])
def test_deploy_commands_name_a_missing_fleet_directory(
        cli: Cli, args: list[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """They said '/nowhere/.compose: no deployment here; run `fleetctl up` first' (exit 1)
    for a fleet directory that is not there, as if `up` could run in it."""
    from fleetctl.cli import deploy as deploy_cli

    monkeypatch.setattr(deploy_cli, "require_docker", lambda: None)
    _, err = cli(*args, code=ExitCode.CONFIG)
    assert err.startswith(f"fleetctl: error: fleet directory {cli.fleet} does not exist")
    assert len(err.splitlines()) == 1


@pytest.mark.parametrize("output", ["text", "json"])
def test_list_shows_what_it_can_and_names_the_files_it_cannot_read(
        fleet: Path, cli: Cli, tmp_path: Path, output: str) -> None:
    """An operator's pass: with keys/server.key gone (a fleet directory restored without
    it) `list` printed one error and nothing else, though fleet.yaml, which it lists, was
    all there. It lists everything, marks the public keys it cannot show, then names each
    file on one error line (exit 3, as the error was)."""
    cli("add-robot", "r2")
    cli("add-user", "a@example.com", "--role", "viewer")
    husky_pub = json.loads(cli("list", "-o", "json")[0])["robot_public_keys"]["husky1"]
    # The operator's own certificate, its key since deleted.
    (tmp_path / "cert.pem").write_bytes((fleet / "server/tls/cert.pem").read_bytes())
    path = fleet / "fleet.yaml"
    assert "\ntls: null\n" in path.read_text()
    tls = f"tls: {{cert: {tmp_path / 'cert.pem'}, key: {tmp_path / 'gone.key'}}}"
    path.write_text(path.read_text().replace("\ntls: null\n", f"\n{tls}\n"))
    (fleet / "keys/server.key").unlink()
    (fleet / "keys/robots/r2.psk").unlink()
    out, err = cli("list", "-o", output, code=ExitCode.CONFIG)
    assert len(err.splitlines()) == 1
    assert err.startswith("fleetctl: error: 3 problems: [1] ")
    problems = re.split(r" \[\d\] ", err.removeprefix("fleetctl: error: 3 problems: [1] "
                                                      ).rstrip("\n"))
    assert problems[0].startswith(f"{fleet}/keys/server.key: key file not found: restore it")
    assert problems[1].startswith(f"{fleet}/fleet.yaml:") and "tls.key: " in problems[1]
    assert str(tmp_path / "gone.key") in problems[1]
    assert problems[2] == (
        f"{fleet}/keys/robots/r2.psk: key file not found (its pair r2.key is there): "
        f"restore it from a backup, or, to give the robot new keys, delete "
        f"{fleet}/keys/robots/r2.key and {fleet}/robots/r2/wireguard/wg0.conf, run "
        "`fleetctl render` and install a new `fleetctl export r2` on the robot")
    if output == "json":
        info = json.loads(out)
        assert [r["name"] for r in info["fleet"]["robots"]] == ["husky1", "r2"]
        assert [u["email"] for u in info["fleet"]["users"]] == ["a@example.com"]
        assert info["server_public_key"] is None
        assert info["robot_public_keys"] == {"husky1": husky_pub}
        assert info["unreadable_robot_keys"] == ["r2"] and info["problems"] == problems
    else:
        assert "server public key: (key file unreadable: see the error)" in out
        assert husky_pub in out and "a@example.com  viewer" in out
        assert [line.split()[-1] for line in out.splitlines() if line.startswith("r2 ")] == [
            "error)"]
    (fleet / "keys/robots/r2.key").unlink()  # both gone, its wg0.conf still there
    _, err = cli("list", code=ExitCode.CONFIG)
    assert f"{fleet}/keys/robots/r2.key and r2.psk: not found, but " in err


def _files(root: Path) -> dict[str, tuple[int, int, bytes]]:
    """Every file under *root*: (inode, mtime in ns, bytes), by path relative to *root*."""
    return {str(p.relative_to(root)): (p.stat().st_ino, p.stat().st_mtime_ns, p.read_bytes())
            for p in root.rglob("*") if p.is_file()}


def test_init_force_dry_run_says_what_the_real_run_then_does(fleet: Path, cli: Cli) -> None:
    """An operator's pass: `init --force --dry-run` said `1 file(s) already up to date`
    (server/server.yaml, judged against the file about to be deleted with server/); the
    real run said the same, never wrote it, and deleting server/ took it: the new fleet
    had no server.yaml. Both now report it created, and the report is what happens on
    disk: created and updated files are new, deleted ones gone, the rest untouched."""
    cli("add-user", "a@example.com", "--role", "viewer")
    args = ("init", str(fleet), "--force", "--endpoint", "vpn.example.com:51820", "-o", "json")

    def changes(out: str) -> list[tuple[str, str]]:
        return [(str(Path(c["path"]).relative_to(fleet)), c["kind"])
                for c in json.loads(out)["outcome"]["changes"]]

    preview = changes(cli(*args, "--dry-run")[0])
    before = _files(fleet)
    done = changes(cli(*args)[0])
    after = _files(fleet)
    assert preview == done
    assert ("server/server.yaml", "create") in done
    deleted = [path for path, kind in done if kind == "delete"]
    written = {path for path, kind in done if kind in ("create", "update")}
    assert sorted(deleted) == ["keys", "robots", "server"]
    assert written <= set(after)
    for path, now in after.items():
        if path in written:
            assert now != before.get(path), path  # a new file (or new bytes)
        else:
            assert now == before[path], path  # untouched: same inode, mtime and bytes
            assert not any(Path(path).is_relative_to(d) for d in deleted), path
    gone = {path for path in before
            if any(Path(path).is_relative_to(d) for d in deleted)} - written
    assert gone and not gone & set(after)
    # The fleet it made is whole: `render` finds every file up to date.
    out, _ = cli("render", "--dry-run")
    assert [line for line in out.splitlines()[1:] if "would" in line] == []


def test_init_given_two_different_directories_is_a_usage_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """`fleetctl init aa --fleet bb` made the fleet in aa and said nothing of bb; the same
    directory twice, or $FLEET_DIR beside the argument (the README's flow with a second
    fleet), is fine: the argument names where the new fleet goes."""
    monkeypatch.chdir(tmp_path)
    assert main(["init", "aa", "--fleet", "bb"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fleetctl: error: ") and "'aa'" in err and "--fleet 'bb'" in err
    assert not (tmp_path / "aa").exists() and not (tmp_path / "bb").exists()
    assert main(["init", "aa", "--fleet", str(tmp_path / "aa")]) == 0
    monkeypatch.setenv("FLEET_DIR", str(tmp_path / "aa"))
    assert main(["init", "cc"]) == 0 and (tmp_path / "cc" / "fleet.yaml").is_file()


def test_init_dry_run_shows_no_key_the_real_run_will_not_use(cli: Cli, tmp_path: Path) -> None:
    """`init --dry-run` printed a server public key made for the preview only: the real
    `init` makes a new key pair, so the key an operator copied from the dry run was false."""
    new = tmp_path / "new"
    out, _ = cli("init", str(new), "--dry-run")
    assert "server public key" not in out
    assert "server WireGuard key pair: would be made by the real run" in out
    assert "a self-signed certificate would be made" in out
    shown, _ = cli("init", str(new), "--dry-run", "-o", "json")
    assert json.loads(shown)["server_public_key"] is None
    out, _ = cli("init", str(new))
    real = re.search(r"^server public key: (\S+)$", out, re.M)
    assert real is not None
    listed, _ = cli("list", "--fleet", str(new))
    assert f"server public key: {real.group(1)}" in listed


@pytest.mark.parametrize("directory", ["keys", "keys/robots", "server", "server/tls",
                                       "robots", "robots/husky1", ".compose"])
def test_a_fleet_directory_that_is_a_file_is_named(fleet: Path, cli: Cli,
                                                   directory: str) -> None:
    """keys/ as a regular file: every command said robot key files were not found (and
    render, with server/ a file, `server/tls: cannot write`, exit 5) instead of naming the
    path that is not a directory."""
    path = fleet / directory
    if path.exists():
        os.rename(path, fleet / "moved-away")
    path.write_text("not a directory\n")
    for args in (["list"], ["render"], ["add-robot", "r2"], ["export", "husky1", "--out",
                                                              str(fleet.parent / "b.tgz")]):
        _, err = cli(*args, code=ExitCode.CONFIG)
        assert err.startswith(f"fleetctl: error: {path}: not a directory but a file (it "
                              "holds "), (args, err)
        assert "not found" not in err and err.count("\n") == 1


def test_the_sync_is_told_which_files_changed(fleet: Path, cli: Cli,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """The running fleet's note says only what changed: it needs the command's changed
    files (remove-user changes auth.yaml, no WireGuard file)."""
    from fleetctl.deploy import live

    seen: list[set[str]] = []

    def record(d: Path, p: Callable[[str], None],
               changed: Collection[Path] | None = None) -> str | None:
        assert changed is not None
        seen.append({str(Path(c).relative_to(d)) for c in changed})
        return None

    monkeypatch.setattr(live, "sync_running", record)
    cli("add-user", "a@example.com", "--role", "viewer")
    cli("remove-user", "a@example.com")
    cli("render")
    assert seen == [{"fleet.yaml", "server/auth.yaml"}] * 2 + [set()]


# --- users scoped to some robots (docs/operator.md, "Users scoped to some robots") --------


def _auth_rules(fleet: Path) -> dict[str, list[tuple[str, str]]]:
    """server/auth.yaml's rules by identity name."""
    raw = yaml.safe_load((fleet / "server/auth.yaml").read_text())
    return {i["name"]: [(r["topic"], r["op"]) for r in i["rules"]] for i in raw["identities"]}


def _stored_users(fleet: Path) -> dict[str, dict[str, object]]:
    return {u["email"]: u for u in yaml.safe_load((fleet / "fleet.yaml").read_text())["users"]}


@pytest.fixture
def two_robots(fleet: Path, cli: Cli) -> Path:
    cli("add-robot", "jackal2")
    cli("add-robot", "husky10")
    return fleet


def test_add_user_scoped_to_robots(two_robots: Path, cli: Cli) -> None:
    fleet = two_robots
    out, _ = cli("add-user", "site@example.com", "--role", "viewer", "--robots", "husky1")
    assert out.startswith("user 'site@example.com' (viewer, robots husky1)\n")
    out, _ = cli("add-user", "ops@example.com", "--role", "operator", "--robots",
                 "jackal2,husky1", "--robots", "husky10", "-o", "json")
    assert json.loads(out)["user"]["robots"] == ["jackal2", "husky1", "husky10"]
    cli("add-user", "all@example.com", "--role", "operator")
    rules = _auth_rules(fleet)
    assert rules["site@example.com"] == [("/husky1/.*", "receive")]
    assert rules["ops@example.com"] == [
        ("/(jackal2|husky1|husky10)/.*", "receive"),
        ("/jackal2/(goal_pose|initialpose)", "send"),
        ("/husky1/(goal_pose|initialpose)", "send"),
        ("/husky10/(goal_pose|initialpose)", "send")]
    assert rules["all@example.com"][0] == ("/[^/]+/.*", "receive")
    stored = _stored_users(fleet)
    assert stored["site@example.com"]["robots"] == ["husky1"]
    assert "robots" not in stored["all@example.com"]
    out, _ = cli("list")
    assert "USER              ROLE      ROBOTS\n" in out
    assert "site@example.com  viewer    husky1\n" in out
    assert "ops@example.com   operator  jackal2,husky1,husky10\n" in out
    assert out.endswith("all@example.com   operator  all\n")
    out, _ = cli("list", "-o", "json")
    assert [u["robots"] for u in json.loads(out)["fleet"]["users"]] == [
        ["husky1"], ["jackal2", "husky1", "husky10"], None]


@pytest.mark.parametrize(("args", "code", "message"), [
    (["--role", "admin", "--robots", "husky1"], ExitCode.USAGE,
     "--robots: an admin may use every robot and cannot be scoped to some (make the user a "
     "viewer or an operator)"),
    (["--role", "viewer", "--robots", "husky1,husky9"], ExitCode.CONFIG,
     "--robots: no robot 'husky9' in {fleet}/fleet.yaml (its robots: husky1)"),
    (["--role", "viewer", "--robots", "husky1,,husky1"], ExitCode.USAGE,
     "--robots: an empty robot name in --robots 'husky1,,husky1'"),
    (["--role", "viewer", "--robots", ""], ExitCode.USAGE,
     "--robots: an empty robot name in --robots ''"),
    (["--role", "operator", "--robots", "husky1", "--robots", "husky1"], ExitCode.USAGE,
     "--robots: robot 'husky1' is given twice"),
])
def test_add_user_robots_errors_change_nothing(fleet: Path, cli: Cli, args: list[str],
                                               code: int, message: str) -> None:
    before = _snapshot(fleet)
    _, err = cli("add-user", "x@example.com", *args, code=code)
    assert err == f"fleetctl: error: {message.format(fleet=fleet)}\n"
    assert _snapshot(fleet) == before


def test_set_user_changes_the_scope_and_keeps_the_token(two_robots: Path, cli: Cli,
                                                        synced: list[Path]) -> None:
    fleet = two_robots
    cli("add-user", "v@example.com", "--role", "viewer")
    unscoped = (fleet / "fleet.yaml").read_bytes()
    token_hash = _stored_users(fleet)["v@example.com"]["token_sha256"]
    before = _snapshot(fleet)
    out, _ = cli("set-user", "v@example.com", "--robots", "jackal2", "--dry-run")
    assert out.startswith("dry run: would set user 'v@example.com' (viewer) robots: jackal2 "
                          "(was: every robot)\n  would update fleet.yaml\n  would update "
                          "server/auth.yaml\n")
    assert _snapshot(fleet) == before
    synced.clear()
    out, _ = cli("set-user", "v@example.com", "--robots", "jackal2,husky1")
    assert out.startswith("set user 'v@example.com' (viewer) robots: jackal2, husky1 (was: "
                          "every robot)\n")
    assert synced == [fleet]  # a running server gets the new auth.yaml
    assert _stored_users(fleet)["v@example.com"] == {
        "email": "v@example.com", "role": "viewer", "robots": ["jackal2", "husky1"],
        "token_sha256": token_hash}
    assert _auth_rules(fleet)["v@example.com"] == [("/(jackal2|husky1)/.*", "receive")]
    _, err = cli("add-user", "v@example.com", "--role", "viewer", code=ExitCode.CONFLICT)
    assert err.endswith("and add them again with --robots jackal2,husky1\n")
    out, _ = cli("set-user", "v@example.com", "--all-robots", "-o", "json")
    result = json.loads(out)
    assert (result["user"]["robots"], result["previous_robots"]) == (None, ["jackal2", "husky1"])
    assert (fleet / "fleet.yaml").read_bytes() == unscoped


@pytest.mark.parametrize(("args", "code", "message"), [
    (["v@example.com"], ExitCode.USAGE,
     "set-user: give --robots NAME[,NAME...] or --all-robots (one of them)"),
    (["v@example.com", "--robots", "husky1", "--all-robots"], ExitCode.USAGE,
     "set-user: give --robots NAME[,NAME...] or --all-robots (one of them)"),
    (["a@example.com", "--robots", "husky1"], ExitCode.USAGE,
     "--robots: an admin may use every robot and cannot be scoped to some (make the user a "
     "viewer or an operator)"),
    (["V@example.com", "--robots", "husky1"], ExitCode.CONFIG,
     "user 'V@example.com' is not in {fleet}/fleet.yaml (there is 'v@example.com')"),
    (["v@example.com", "--robots", "jackal2"], ExitCode.CONFIG,
     "--robots: no robot 'jackal2' in {fleet}/fleet.yaml (its robots: husky1)"),
])
def test_set_user_errors_change_nothing(fleet: Path, cli: Cli, args: list[str], code: int,
                                        message: str) -> None:
    cli("add-user", "v@example.com", "--role", "viewer")
    cli("add-user", "a@example.com", "--role", "admin")
    before = _snapshot(fleet)
    _, err = cli("set-user", *args, code=code)
    assert err == f"fleetctl: error: {message.format(fleet=fleet)}\n"
    assert _snapshot(fleet) == before


def test_remove_robot_leaves_the_scopes_that_named_it(two_robots: Path, cli: Cli) -> None:
    fleet = two_robots
    cli("add-user", "ops@example.com", "--role", "operator", "--robots", "husky1,jackal2")
    cli("add-user", "site@example.com", "--role", "viewer", "--robots", "jackal2")
    before = _snapshot(fleet)
    _, err = cli("remove-robot", "jackal2", code=ExitCode.CONFLICT)
    assert err == ("fleetctl: error: robot 'jackal2' is the only robot of user "
                   "'site@example.com' (fleet.yaml users[].robots): give them another first "
                   "(`fleetctl set-user site@example.com --robots NAME`, or --all-robots) or "
                   "remove them (`fleetctl remove-user site@example.com`); nothing was "
                   "changed\n")
    assert _snapshot(fleet) == before
    cli("set-user", "site@example.com", "--robots", "husky10")
    _, err = cli("remove-robot", "jackal2")
    assert err.splitlines()[0] == ("fleetctl: warning: user 'ops@example.com' is scoped to "
                                   f"husky1 now (robot 'jackal2' left their robots in {fleet}"
                                   "/fleet.yaml)")
    assert _stored_users(fleet)["ops@example.com"]["robots"] == ["husky1"]
    assert _auth_rules(fleet)["ops@example.com"] == [
        ("/husky1/.*", "receive"), ("/husky1/(goal_pose|initialpose)", "send")]
