"""Rendering: golden files, idempotence, reproducibility, permissions, schemas."""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import stat
from pathlib import Path

import jinja2
import pytest
import yaml

from fleetctl.deploy import operations as ops
from fleetctl.deploy.export import export_robot
from fleetctl.deploy.files import ChangeKind, FileWrite, edit_state, stamp, write_file
from fleetctl.deploy.render import render_template
from fleetctl.deploy.topics import DEFAULT_PUBLISH
from fleetctl.errors import ConfigError
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


def test_render_restores_deleted_files_and_modes(fleet_dir: Path) -> None:
    before = {k: v[:2] for k, v in _snapshot(fleet_dir).items()}
    shutil.rmtree(fleet_dir / "robots")
    (fleet_dir / "server" / "wireguard" / "wg0.conf").chmod(0o644)
    ops.render_fleet(fleet_dir)
    assert {k: v[:2] for k, v in _snapshot(fleet_dir).items()} == before


def test_hand_edit_is_refused_then_forced(fleet_dir: Path) -> None:
    client = fleet_dir / "robots/husky1/client.yaml"
    client.write_text(client.read_text().replace("/odom", "/odometry"))
    before = _snapshot(fleet_dir)
    with pytest.raises(ConfigError) as info:
        ops.render_fleet(fleet_dir)
    message = str(info.value)
    assert message == (
        f"{client} was edited by hand: put topics in fleet.yaml robots[0].publish / "
        "subscribe / battery_topic, then run `fleetctl render --force` to overwrite")
    assert "\n" not in message
    assert _snapshot(fleet_dir) == before  # nothing written, not even other files
    with pytest.raises(ConfigError, match="was edited by hand"):
        ops.add_user(fleet_dir, "new@example.com", "viewer")  # every re-render refuses
    assert _snapshot(fleet_dir) == before
    ops.render_fleet(fleet_dir, force=True)
    assert "/odometry" not in client.read_text()
    assert {c.kind for c in ops.render_fleet(fleet_dir).changes} == {ChangeKind.UNCHANGED}


@pytest.mark.parametrize("relpath", ["server/auth.yaml", "server/wireguard/wg0.conf",
                                     "robots/jackal2/wireguard/wg0.conf", "server/server.yaml"])
def test_every_generated_file_is_guarded(fleet_dir: Path, relpath: str) -> None:
    path = fleet_dir / relpath
    path.write_text(path.read_text() + "# mine\n")
    with pytest.raises(ConfigError, match=f"{relpath} was edited by hand: .+fleet.yaml"):
        ops.render_fleet(fleet_dir)
    assert path.read_text().endswith("# mine\n")


def test_a_generated_file_replaced_by_a_link_is_said_to_be_one(fleet_dir: Path) -> None:
    conf = fleet_dir / "robots/husky1/wireguard/wg0.conf"
    target = fleet_dir.parent / "elsewhere.conf"
    target.write_text(conf.read_text())  # even the same content: never written through
    conf.unlink()
    conf.symlink_to(target)
    with pytest.raises(ConfigError, match=r"wg0\.conf is a symbolic link, which fleetctl "
                                          r"never writes through: set ip and mtu_bytes"):
        ops.render_fleet(fleet_dir)
    assert conf.is_symlink()


def test_digest_line_is_the_sha256_of_the_rest(fleet_dir: Path) -> None:
    for rel in GENERATED[1:]:
        first, rest = (fleet_dir / rel).read_bytes().split(b"\n", 1)
        assert first == b"# fleetctl: generated, sha256=" + (
            hashlib.sha256(rest).hexdigest().encode()), rel


def test_file_without_digest_line(fleet_dir: Path) -> None:
    """Old fleets: a file without the line is kept unless it is exactly what we'd write."""
    auth = fleet_dir / "server/auth.yaml"
    auth.write_text(auth.read_text().split("\n", 1)[1])  # as if written before digests
    ops.render_fleet(fleet_dir)
    assert auth.read_text().startswith("# fleetctl: generated")
    auth.write_text("hand made\n")
    with pytest.raises(ConfigError, match="has no fleetctl digest line"):
        ops.render_fleet(fleet_dir)
    assert auth.read_text() == "hand made\n"


def test_edit_state_and_stamp() -> None:
    text = stamp("a: 1\n")
    assert edit_state(text.encode(), text) == "generated"
    assert edit_state(text.encode(), stamp("a: 2\n")) == "generated"  # untouched, outdated
    assert edit_state(text.encode().replace(b"1", b"3"), text) == "edited"
    assert edit_state(b"a: 1\n", text) == "generated"
    assert edit_state(b"a: 3\n", text) == "unstamped"
    assert stamp("x\n", markdown=True).startswith("<!-- fleetctl: generated, sha256=")
    md = stamp("# Title\n", markdown=True)
    assert edit_state(md.encode(), md) == "generated"
    assert edit_state(md.encode() + b"more\n", md) == "edited"


def test_render_never_rewrites_fleet_yaml(fleet_dir: Path) -> None:
    path = fleet_dir / "fleet.yaml"
    path.write_text("# my notes\n" + path.read_text())
    ops.render_fleet(fleet_dir)
    assert path.read_text().startswith("# my notes\n")


def test_symlink_at_a_secret_target_is_replaced_not_followed(fleet_dir: Path,
                                                              tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.write_text("keep\n")
    conf = fleet_dir / "robots/husky1/wireguard/wg0.conf"
    expected = conf.read_bytes()
    conf.unlink()
    conf.symlink_to(victim)
    ops.render_fleet(fleet_dir, force=True)
    assert victim.read_text() == "keep\n"
    assert not conf.is_symlink() and conf.read_bytes() == expected
    assert stat.S_IMODE(conf.stat().st_mode) == 0o600


def test_temp_file_symlink_is_not_followed(tmp_path: Path) -> None:
    victim = tmp_path / "victim"
    victim.write_text("keep\n")
    target = tmp_path / "d" / "secret"
    target.parent.mkdir()
    (target.parent / f".secret.{os.getpid()}.tmp").symlink_to(victim)
    write_file(FileWrite(target, b"s3cret\n", 0o600, 0o700))
    assert victim.read_text() == "keep\n" and target.read_bytes() == b"s3cret\n"


TLS_FILES = ("keys/tls.key", "server/tls/cert.pem")


def test_same_inputs_same_bytes(tmp_path: Path, fleet_dir: Path) -> None:
    other = make_fleet(tmp_path / "again")
    mine, theirs = _snapshot(fleet_dir), _snapshot(other)
    assert mine.keys() == theirs.keys()
    for key in mine.keys() - set(TLS_FILES):  # a certificate is signed with a random nonce
        assert mine[key][:2] == theirs[key][:2], key


def test_secret_permissions(fleet_dir: Path) -> None:
    secret_files = ["keys/server.key", "keys/robots/husky1.key", "keys/robots/husky1.psk",
                    "keys/tls.key", "server/wireguard/wg0.conf",
                    "robots/husky1/wireguard/wg0.conf"]
    assert stat.S_IMODE((fleet_dir / "server/tls/cert.pem").stat().st_mode) == 0o644
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
    assert topics == {t.topic for t in DEFAULT_PUBLISH}
    assert [s["local_topic"] for s in client["subscribe"]] == ["/goal_pose", "/initialpose"]


def test_strict_undefined() -> None:
    with pytest.raises(jinja2.UndefinedError):
        render_template("server/server.yaml.j2", fleet_name="x")


def test_export_directory_matches_the_fleet_files(fleet_dir: Path, tmp_path: Path) -> None:
    bundle = export_robot(fleet_dir, "husky1", tmp_path / "b").path
    assert {"README.md", "client.yaml", "wg0.conf"} <= {p.name for p in bundle.iterdir()}
    assert stat.S_IMODE(bundle.stat().st_mode) == 0o700
    assert stat.S_IMODE((bundle / "wg0.conf").stat().st_mode) == 0o600
    assert (bundle / "wg0.conf").read_bytes() == (
        fleet_dir / "robots/husky1/wireguard/wg0.conf").read_bytes()
    assert (bundle / "README.md").read_text().startswith("<!-- fleetctl: generated, sha256=")
    # The tarball and the rest of the bundle: tests/deploy/test_bundle*.py (bundle.py).


MAPPER = """\
- name: mapper
  ip: 10.8.0.30
  publish:
    - {topic: /map, type: nav_msgs/msg/OccupancyGrid, priority: 2, rate_limit_hz: 0.5,
       compression: deflate}
    - {topic: /gps/fix, type: sensor_msgs/msg/NavSatFix, priority: 4.5}
    - {topic: /events, type: std_msgs/msg/String, no_drop: true, rate_limit_hz: null}
  subscribe:
    - {remote_topic: /husky1/map, type: nav_msgs/msg/OccupancyGrid, local_topic: /peer_map}
  battery_topic: /battery_state
  location: "yard: north # gate 'B'"
"""


def _add_mapper(fleet_dir: Path) -> None:
    path = fleet_dir / "fleet.yaml"
    path.write_text(path.read_text().replace("users:\n", MAPPER + "users:\n", 1))


def test_custom_topics_render_and_load_in_the_client(fleet_dir: Path) -> None:
    from fleetctl.client.config import load_client_config

    _add_mapper(fleet_dir)
    ops.render_fleet(fleet_dir)
    actual = (fleet_dir / "robots/mapper/client.yaml").read_text()
    golden = GOLDEN / "robots__mapper__client.yaml"
    if os.environ.get("UPDATE_GOLDEN"):
        golden.write_text(actual)
    assert actual == golden.read_text()
    cfg = load_client_config(fleet_dir / "robots/mapper/client.yaml")
    assert [(p.topic, p.remote_topic, p.compression) for p in cfg.publish] == [
        ("/map", "/mapper/map", "deflate"), ("/gps/fix", "/mapper/gps/fix", "none"),
        ("/events", "/mapper/events", "none")]
    assert cfg.publish[0].rate_limit_hz == 0.5 and cfg.publish[2].no_drop
    assert [s.local_topic for s in cfg.subscribe] == ["/goal_pose", "/initialpose", "/peer_map"]
    assert cfg.status.battery_topic == "/battery_state"
    assert cfg.status.location == "yard: north # gate 'B'"  # YAML-escaped, read back whole
    # Listing the topic in subscribe is what lets the robot receive it.
    auth = yaml.safe_load((fleet_dir / "server/auth.yaml").read_text())
    mapper = next(i for i in auth["identities"] if i["name"] == "mapper")
    assert {"topic": "/husky1/map", "op": "receive"} in mapper["rules"]


MEDIA = """\
- name: sensorbot
  ip: 10.8.0.31
  publish:
    - {topic: /camera/image_raw, type: sensor_msgs/msg/Image, priority: 1,
       video: {codec: vp9, max_bitrate_kbps: 800}}
    - {topic: /camera/compressed, type: sensor_msgs/msg/CompressedImage, video: {}}
    - {topic: /points, type: sensor_msgs/msg/PointCloud2, viewer_cloud: {resolution_m: 0.02}}
    - {topic: /map, type: nav_msgs/msg/OccupancyGrid, video: null, viewer_cloud: null}
  tf: {translation_delta_m: 0.05, max_rate_hz: 5}
"""


def test_media_keys_render_and_load_in_the_client(fleet_dir: Path) -> None:
    from fleetctl.client.config import TfSpec, VideoSpec, ViewerCloudSpec, load_client_config

    path = fleet_dir / "fleet.yaml"
    path.write_text(path.read_text().replace("users:\n", MEDIA + "users:\n", 1))
    ops.render_fleet(fleet_dir)
    actual = (fleet_dir / "robots/sensorbot/client.yaml").read_text()
    golden = GOLDEN / "robots__sensorbot__client.yaml"
    if os.environ.get("UPDATE_GOLDEN"):
        golden.write_text(actual)
    assert actual == golden.read_text()
    cfg = load_client_config(fleet_dir / "robots/sensorbot/client.yaml")
    assert [(p.video, p.viewer_cloud) for p in cfg.publish] == [
        (VideoSpec(codec="vp9", max_bitrate_kbps=800), None),
        (VideoSpec(), None),
        (None, ViewerCloudSpec(resolution_m=0.02)),
        (None, None)]
    assert cfg.tf == TfSpec(translation_delta_m=0.05, max_rate_hz=5.0)
    # The robot sends its viewer cloud and TF under its own namespace: no new auth rule.
    auth = yaml.safe_load((fleet_dir / "server/auth.yaml").read_text())
    bot = next(i for i in auth["identities"] if i["name"] == "sensorbot")
    assert {"topic": "/sensorbot/.*", "op": "send"} in bot["rules"]


def test_new_robots_send_tf_and_without_tf_in_fleet_yaml_none_is_rendered(
        fleet_dir: Path) -> None:
    from fleetctl.client.config import TfSpec, load_client_config

    client = fleet_dir / "robots/husky1/client.yaml"
    assert "video:" not in client.read_text()
    assert load_client_config(client).tf == TfSpec()  # add-robot's default
    fleet_yaml = fleet_dir / "fleet.yaml"
    text = fleet_yaml.read_text()
    without = re.sub(r"\n  tf:\n(?:    .*\n)+", "\n", text)
    assert without != text
    fleet_yaml.write_text(without)
    ops.render_fleet(fleet_dir)
    assert "tf:" not in client.read_text()
    assert load_client_config(client).tf is None


def test_default_topics_client_config_loads(fleet_dir: Path) -> None:
    from fleetctl.client.config import COMPRESSIONS, load_client_config
    from fleetctl.deploy.topics import COMPRESSIONS as FLEET_COMPRESSIONS

    assert FLEET_COMPRESSIONS == COMPRESSIONS
    cfg = load_client_config(fleet_dir / "robots/husky1/client.yaml")
    assert len(cfg.publish) == len(DEFAULT_PUBLISH) and cfg.status.battery_topic is None


def test_no_endpoint_robot_config_has_no_endpoint_line(tmp_path: Path) -> None:
    fleet_dir = tmp_path / "f"
    ops.create_fleet(fleet_dir)
    result = ops.add_robot(fleet_dir, "r1")
    conf = (fleet_dir / "robots/r1/wireguard/wg0.conf").read_text()
    assert "Endpoint" not in conf.replace("# No Endpoint", "")
    assert "PersistentKeepalive = 25" in conf
    assert len(result.outcome.warnings) == 1
    assert "fleetctl set-endpoint HOST:PORT" in result.outcome.warnings[0]


def test_server_yaml_web_section_and_server_loader(fleet_dir: Path) -> None:
    server = yaml.safe_load((fleet_dir / "server/server.yaml").read_text())
    assert server["web"] == {"listen_host": "0.0.0.0", "listen_port": 8443,
                             "tls_cert": "tls/cert.pem", "tls_key": "../keys/tls.key"}
    assert server["listen_port"] == 8080 and server["tls_cert"] is None
    base = fleet_dir / "server"
    assert (base / server["web"]["tls_cert"]).is_file()
    assert (base / server["web"]["tls_key"]).is_file()


@pytest.mark.parametrize("text", ["plain", 'quo"te \\ back', "new\nline", "tab\there",
                                  "\u2028sep\x85", "caf\u00e9 \U0001f916", "#not: a comment",
                                  "- [x]", "", "null", "yes"])
def test_yaml_filter_round_trips(text: str) -> None:
    from fleetctl.deploy.render import yaml_scalar

    rendered = yaml_scalar(text)
    assert "\n" not in rendered and "\u2028" not in rendered and "\x85" not in rendered
    assert yaml.safe_load(f"k: {rendered}\n") == {"k": text}


def test_yaml_filter_refuses_non_finite() -> None:
    from fleetctl.deploy.render import yaml_scalar

    with pytest.raises(ValueError):
        yaml_scalar(float("nan"))


@pytest.mark.parametrize("value", ["x\n[Peer]", "x\rAllowedIPs = 0.0.0.0/0", "a\x00",
                                   "a\u2028b", "key # cut", " padded"])
def test_wireguard_filter_refuses_line_breaks(value: str) -> None:
    from fleetctl.deploy.render import wg_value

    with pytest.raises(ValueError):
        wg_value(value)


def test_fleet_name_cannot_inject_into_wireguard(fleet_dir: Path) -> None:
    path = fleet_dir / "fleet.yaml"
    path.write_text(path.read_text().replace(
        "name: campus", 'name: "campus\\n[Peer]\\nAllowedIPs = 0.0.0.0/0"'))
    before = _snapshot(fleet_dir)
    with pytest.raises(ConfigError, match=r"fleet\.yaml:5: name: fleet name .* must be ASCII"):
        ops.render_fleet(fleet_dir)
    assert _snapshot(fleet_dir) == before


def test_relay_replicas_reach_every_robots_client_yaml_and_back(fleet_dir: Path) -> None:
    from fleetctl.client.config import load_client_config

    config = fleet_dir / "robots/husky1/client.yaml"
    one = config.read_bytes()
    outcome = ops.set_relay_replicas(fleet_dir, 3)
    changed = {str(c.path.relative_to(fleet_dir)) for c in outcome.changes
               if c.kind is not ChangeKind.UNCHANGED}
    assert changed == {"fleet.yaml", "robots/husky1/client.yaml", "robots/jackal2/client.yaml"}
    # What the robot's client reads from it: the first replica, then the others to fail
    # over to (replica i on server_port + i).
    assert load_client_config(config).server_urls == (
        "ws://10.8.0.1:8080/", "ws://10.8.0.1:8081/", "ws://10.8.0.1:8082/")
    # The new files are the generated ones, not hand edits: render leaves them as they are.
    assert {c.kind for c in ops.render_fleet(fleet_dir).changes} == {ChangeKind.UNCHANGED}
    ops.set_relay_replicas(fleet_dir, 1)
    assert config.read_bytes() == one
    assert "relay_replicas" not in (fleet_dir / "fleet.yaml").read_text()
