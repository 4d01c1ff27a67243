"""Unit tests of the demo's fleet files (design.md sections 3 to 5)."""

from __future__ import annotations

import hashlib
import ipaddress
import stat
from pathlib import Path

import pytest
import yaml

from fleetctl.client.config import load_client_config
from fleetctl.demo.fleet import create_demo_fleet


def test_demo_fleet_files_follow_the_contracts(tmp_path: Path) -> None:
    fleet = create_demo_fleet(tmp_path, 2, port=0, base_domain_id=20)
    assert fleet.port > 0
    assert [r.name for r in fleet.robots] == ["robot1", "robot2"]
    assert [r.address for r in fleet.robots] == ["127.0.1.2", "127.0.1.3"]
    assert [r.ros_domain_id for r in fleet.robots] == [20, 21]
    server = yaml.safe_load(fleet.server_config.read_text())
    assert server["listen_port"] == fleet.port
    assert server["auth_map"] == "auth.yaml"
    auth = yaml.safe_load((tmp_path / "server" / "auth.yaml").read_text())
    by_name = {identity["name"]: identity for identity in auth["identities"]}
    assert by_name["robot1"]["ip"] == "127.0.1.2"
    viewer_hash = hashlib.sha256(fleet.viewer_token.encode()).hexdigest()
    assert by_name["demo-viewer"]["token_sha256"] == viewer_hash
    assert fleet.viewer_token not in (tmp_path / "server" / "auth.yaml").read_text()


def test_client_configs_load_with_the_client_loader(tmp_path: Path) -> None:
    fleet = create_demo_fleet(tmp_path, 1, port=9999, base_domain_id=30)
    config = load_client_config(fleet.robots[0].client_config)
    assert config.server_url == "ws://127.0.0.1:9999/"
    assert config.bind_address == "127.0.1.2"
    remote = {spec.remote_topic: spec for spec in config.publish}
    assert remote["/robot1/events"].no_drop
    assert remote["/robot1/scan"].type == "sensor_msgs/msg/LaserScan"
    # The cloud goes out deflate-compressed: the webviz inflates it in the browser.
    assert remote["/robot1/points"].compression == "deflate"
    assert {s.compression for s in config.publish} == {"none", "deflate"}
    assert {s.local_topic for s in config.subscribe} == {"/goal_pose", "/initialpose"}
    assert config.status.battery_topic == "/battery"
    assert config.status.location == "demo room (simulated, 10 x 8 m)"  # the Location column


def test_the_demo_shows_its_camera_as_video_and_a_viewer_cloud(tmp_path: Path) -> None:
    """The demo's Video panel said "no video yet: ... fleet.yaml has a video: section"
    (the demo has no fleet.yaml) and its 3D scene had no cloud unless the Cloud panel was
    on: the camera now goes out as H.264 and the cloud also as a viewer cloud."""
    fleet = create_demo_fleet(tmp_path, 1, port=9999, base_domain_id=30)
    remote = {spec.remote_topic: spec
              for spec in load_client_config(fleet.robots[0].client_config).publish}
    camera = remote["/robot1/camera/image_raw"]
    assert camera.type == "sensor_msgs/msg/Image"
    assert camera.video is not None and camera.video.codec == "h264"
    assert remote["/robot1/points"].viewer_cloud is not None


def test_files_are_private_and_tokens_stay_out_of_repr(tmp_path: Path) -> None:
    fleet = create_demo_fleet(tmp_path, 1, port=1, base_domain_id=20)
    mode = stat.S_IMODE((tmp_path / "server" / "auth.yaml").stat().st_mode)
    assert mode == 0o600
    assert fleet.operator_token not in repr(fleet)


@pytest.mark.parametrize(("count", "base"), [(0, 20), (251, 0), (2, 232), (1, -1)])
def test_bad_counts_and_domains_are_rejected(tmp_path: Path, count: int, base: int) -> None:
    with pytest.raises(ValueError):
        create_demo_fleet(tmp_path, count, port=1, base_domain_id=base)


def test_server_files_load_with_the_server_loaders(tmp_path: Path) -> None:
    from fleetctl.server.authmap import load_auth_map
    from fleetctl.server.config import load_server_config

    fleet = create_demo_fleet(tmp_path, 2, port=4321, base_domain_id=20)
    config = load_server_config(fleet.server_config)
    assert config.listen_port == 4321
    auth = load_auth_map(config.auth_map)
    assert [i.name for i in auth.match_address(ipaddress.ip_address("127.0.1.3"))] == ["robot2"]
    assert auth.match_token(fleet.operator_token) is not None
    assert auth.match_token("not-a-token") is None


def test_record_adds_a_bounded_recording_the_server_loads(tmp_path: Path) -> None:
    """The demo had no way to record: its server.yaml is written at every start, so a
    team trying recording and replay had to build a fleet of their own first."""
    from fleetctl.server.config import load_server_config

    plain = create_demo_fleet(tmp_path / "a", 1, port=4321, base_domain_id=20)
    assert load_server_config(plain.server_config).recording is None
    fleet = create_demo_fleet(tmp_path / "b", 2, port=4321, base_domain_id=20, record=True)
    recording = load_server_config(fleet.server_config).recording
    assert recording is not None
    assert recording.directory == tmp_path / "b" / "server" / "recordings"
    assert recording.max_total_bytes == 1 << 30 and recording.max_file_bytes == 64 << 20
