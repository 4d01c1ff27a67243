"""Rendering: golden files, idempotence, reproducibility, permissions, schemas."""

from __future__ import annotations

import os
import shutil
import stat
import tarfile
from pathlib import Path

import jinja2
import pytest
import yaml

from fleetctl.deploy import operations as ops
from fleetctl.deploy.export import export_robot
from fleetctl.deploy.files import ChangeKind
from fleetctl.deploy.render import render_template
from tests.deploy.conftest import make_fleet

GOLDEN = Path(__file__).parent / "golden"
GENERATED = [
    "fleet.yaml",
    "server/server.yaml",
    "server/auth.yaml",
    "server/wireguard/wg0.conf",
    "robots/husky1/client.yaml",
    "robots/husky1/wireguard/wg0.conf",
    "robots/jackal2/client.yaml",
    "robots/jackal2/wireguard/wg0.conf",
]


def _snapshot(root: Path) -> dict[str, tuple[bytes, int, int]]:
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file():
            st = p.stat()
            out[str(p.relative_to(root))] = (p.read_bytes(), stat.S_IMODE(st.st_mode),
                                             st.st_mtime_ns)
    return out


@pytest.mark.parametrize("relpath", GENERATED)
def test_golden(fleet_dir: Path, relpath: str) -> None:
    golden = GOLDEN / relpath.replace("/", "__")
    actual = (fleet_dir / relpath).read_text()
    if os.environ.get("UPDATE_GOLDEN"):
        golden.write_text(actual)
    assert actual == golden.read_text(), f"{relpath} differs from {golden} (UPDATE_GOLDEN=1)"


def test_render_twice_changes_nothing(fleet_dir: Path) -> None:
    before = _snapshot(fleet_dir)
    outcome = ops.render_fleet(fleet_dir)
    assert {c.kind for c in outcome.changes} == {ChangeKind.UNCHANGED}
    assert _snapshot(fleet_dir) == before  # bytes, modes and mtimes


def test_render_restores_deleted_and_edited_files(fleet_dir: Path) -> None:
    before = {k: v[:2] for k, v in _snapshot(fleet_dir).items()}
    shutil.rmtree(fleet_dir / "robots")
    (fleet_dir / "server" / "auth.yaml").write_text("hand edit\n")
    (fleet_dir / "server" / "wireguard" / "wg0.conf").chmod(0o644)
    ops.render_fleet(fleet_dir)
    assert {k: v[:2] for k, v in _snapshot(fleet_dir).items()} == before


def test_same_inputs_same_bytes(tmp_path: Path, fleet_dir: Path) -> None:
    other = make_fleet(tmp_path / "again")
    mine, theirs = _snapshot(fleet_dir), _snapshot(other)
    assert mine.keys() == theirs.keys()
    for key in mine:
        assert mine[key][:2] == theirs[key][:2], key


def test_secret_permissions(fleet_dir: Path) -> None:
    secret_files = ["keys/server.key", "keys/robots/husky1.key", "keys/robots/husky1.psk",
                    "server/wireguard/wg0.conf", "robots/husky1/wireguard/wg0.conf"]
    for rel in secret_files:
        assert stat.S_IMODE((fleet_dir / rel).stat().st_mode) == 0o600, rel
    for rel in ["keys", "keys/robots", "server/wireguard", "robots/husky1/wireguard"]:
        assert stat.S_IMODE((fleet_dir / rel).stat().st_mode) == 0o700, rel


def test_auth_map_schema_and_rules(fleet_dir: Path) -> None:
    doc = yaml.safe_load((fleet_dir / "server/auth.yaml").read_text())
    assert doc["version"] == 1
    by_name = {i["name"]: i for i in doc["identities"]}
    assert by_name["husky1"]["ip"] == "10.8.0.2"
    assert by_name["husky1"]["rules"] == [
        {"topic": "/husky1/.*", "op": "send"},
        {"topic": "/husky1/(goal_pose|initialpose)", "op": "receive"},
    ]
    assert by_name["viewer@example.com"]["rules"] == [{"topic": "/[^/]+/.*", "op": "receive"}]
    assert {"topic": "/jackal2/(goal_pose|initialpose)", "op": "send"} in (
        by_name["operator@example.com"]["rules"])
    assert by_name["admin@example.com"]["rules"] == [{"topic": ".*", "op": "both"}]
    for identity in doc["identities"]:
        assert len({"ip", "cidr", "token_sha256"} & identity.keys()) == 1


def test_server_and_client_config_schema(fleet_dir: Path) -> None:
    server = yaml.safe_load((fleet_dir / "server/server.yaml").read_text())
    assert server["listen_port"] == 8080 and server["auth_map"] == "auth.yaml"
    # Every server limit is written out (an operator sees what they may tune), at its
    # default, and the file passes the server's own validation.
    from dataclasses import fields

    from fleetctl.server.config import ServerLimits, load_server_config

    assert set(server["limits"]) == {f.name for f in fields(ServerLimits)}
    assert load_server_config(fleet_dir / "server/server.yaml").limits == ServerLimits()
    client = yaml.safe_load((fleet_dir / "robots/jackal2/client.yaml").read_text())
    assert client["server_url"] == "ws://10.8.0.1:8080/"
    assert client["robot_name"] == "jackal2" and client["bind_address"] == "10.8.0.20"
    topics = {p["topic"] for p in client["publish"]}
    assert topics == {"/pose", "/odom", "/scan", "/camera/image/compressed", "/points", "/events"}
    assert [s["local_topic"] for s in client["subscribe"]] == ["/goal_pose", "/initialpose"]


def test_strict_undefined() -> None:
    with pytest.raises(jinja2.UndefinedError):
        render_template("server/server.yaml.j2", fleet_name="x")


def test_export_directory_and_tarball(fleet_dir: Path, tmp_path: Path) -> None:
    bundle = export_robot(fleet_dir, "husky1", tmp_path / "b").path
    assert sorted(p.name for p in bundle.iterdir()) == ["README.md", "client.yaml", "wg0.conf"]
    assert stat.S_IMODE(bundle.stat().st_mode) == 0o700
    assert stat.S_IMODE((bundle / "wg0.conf").stat().st_mode) == 0o600
    assert (bundle / "wg0.conf").read_bytes() == (
        fleet_dir / "robots/husky1/wireguard/wg0.conf").read_bytes()
    assert "wg-quick up ./wg0.conf" in (bundle / "README.md").read_text()
    (tmp_path / "t1").mkdir(mode=0o755)
    (tmp_path / "t1").chmod(0o755)
    first = export_robot(fleet_dir, "husky1", tmp_path / "t1" / "husky1.tar.gz").path
    second = export_robot(fleet_dir, "husky1", tmp_path / "t2" / "husky1.tar.gz").path
    assert first.read_bytes() == second.read_bytes()
    assert stat.S_IMODE(first.stat().st_mode) == 0o600
    assert stat.S_IMODE(first.parent.stat().st_mode) == 0o755  # the caller's dir: untouched
    with tarfile.open(first) as tar:
        names = {m.name: m.mode for m in tar.getmembers()}
        assert names["husky1/wg0.conf"] == 0o600
        wg = tar.extractfile("husky1/wg0.conf")
        assert wg is not None and wg.read() == (bundle / "wg0.conf").read_bytes()
