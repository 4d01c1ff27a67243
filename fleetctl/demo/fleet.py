"""The demo's temporary fleet: server config, auth map, robot client configs and tokens.

Files follow the contracts of docs/design.md sections 3 to 5 and 7. Robots are identified by
source IP exactly as on a real fleet: robot *i* (0-based) is ``127.0.1.(i + 2)`` on loopback
(its client binds that address), so the server's address rules are exercised for real.
"""

from __future__ import annotations

import secrets
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from fleetctl.deploy.fleet import MAX_ROS_DOMAIN_ID
from fleetctl.tokens import hash_token

# (local topic, type, priority, rate limit in Hz or None, no_drop, compression):
# design.md section 7. The point cloud is deflated, so the web page inflates it in the
# browser (the 240 kB cloud of wall points shrinks by about 8 %; zstd would save as much but
# no browser decodes it). The sim's /map is TRANSIENT_LOCAL: the client sends it latched
# (48 kB, not worth compressing), the server keeps it for viewers who open the page later.
DEFAULT_PUBLISH: tuple[tuple[str, str, float, float | None, bool, str], ...] = (
    ("/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", 2.0, 10.0, False, "none"),
    ("/odom", "nav_msgs/msg/Odometry", 1.0, 10.0, False, "none"),
    ("/scan", "sensor_msgs/msg/LaserScan", 1.0, 10.0, False, "none"),
    ("/camera/image/compressed", "sensor_msgs/msg/CompressedImage", 0.5, 5.0, False, "none"),
    ("/points", "sensor_msgs/msg/PointCloud2", 0.25, 5.0, False, "deflate"),
    ("/events", "std_msgs/msg/String", 4.0, None, True, "none"),
    ("/map", "nav_msgs/msg/OccupancyGrid", 0.25, 1.0, False, "none"),
    ("/camera/image_raw", "sensor_msgs/msg/Image", 0.5, None, False, "none"),
)
# The raw camera goes out as H.264 video (the page's Video panel decodes it with
# WebCodecs), and the cloud also as a viewer cloud (the 3D scene draws it without the
# full cloud): what a robotics team would configure, so the demo shows both.
MEDIA: dict[str, dict[str, Any]] = {
    "/camera/image_raw": {"video": {"codec": "h264", "max_bitrate_kbps": 1000}},
    "/points": {"viewer_cloud": {"resolution_m": 0.05}},
}
# Rate (Hz) of the sims' raw camera: a real camera runs 15-30 Hz; 10 keeps two robots'
# synthetic pictures and H.264 encoders at about a fifth of one core.
CAMERA_HZ = 10.0
DEFAULT_SUBSCRIBE: tuple[tuple[str, str], ...] = (
    ("goal_pose", "geometry_msgs/msg/PoseStamped"),
    ("initialpose", "geometry_msgs/msg/PoseWithCovarianceStamped"),
)


@dataclass(frozen=True)
class DemoRobot:
    """One simulated robot of the demo.

    Attributes:
        name: robot name (topic prefix ``/<name>/``).
        address: loopback source address its client binds; the server identifies it by it.
        ros_domain_id: ``ROS_DOMAIN_ID`` of its sim and client processes.
        client_config: path of its ``client.yaml``.
    """

    name: str
    address: str
    ros_domain_id: int
    client_config: Path


@dataclass(frozen=True)
class DemoFleet:
    """Everything the demo wrote, and the secrets a person needs to use it.

    Attributes:
        root: the temporary fleet directory.
        server_config: path of ``server.yaml``.
        host: address the server listens on.
        port: server port (WebSocket and HTTP).
        robots: the simulated robots.
        viewer_token: token that may receive every topic (shown to the user).
        operator_token: token that may also send goal and initial poses.
    """

    root: Path
    server_config: Path
    host: str
    port: int
    robots: tuple[DemoRobot, ...]
    viewer_token: str
    operator_token: str

    @property
    def ws_url(self) -> str:
        """The server's WebSocket URL."""
        return f"ws://{self.host}:{self.port}/"

    @property
    def http_url(self) -> str:
        """The server's HTTP base URL (``/healthz``, ``/robots``, ``/metrics``)."""
        return f"http://{self.host}:{self.port}"

    def __repr__(self) -> str:  # tokens never appear in a repr
        return f"DemoFleet(root={self.root!s}, port={self.port}, robots={len(self.robots)})"


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (the server binds it right after)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def robot_names(count: int) -> tuple[str, ...]:
    """``robot1`` ... ``robotN``."""
    return tuple(f"robot{i + 1}" for i in range(count))


def auth_map(robots: tuple[DemoRobot, ...], viewer_token: str, operator_token: str) -> Any:
    """The auth map (design.md section 3) as plain data."""
    identities: list[dict[str, Any]] = [
        {
            "name": robot.name,
            "ip": robot.address,
            "rules": [
                {"topic": f"/{robot.name}/.*", "op": "send"},
                {"topic": f"/{robot.name}/(goal_pose|initialpose)", "op": "receive"},
            ],
        }
        for robot in robots
    ]
    identities.append(
        {
            "name": "demo-viewer",
            "token_sha256": hash_token(viewer_token),
            "rules": [{"topic": ".*", "op": "receive"}],
        }
    )
    identities.append(
        {
            "name": "demo-operator",
            "token_sha256": hash_token(operator_token),
            "rules": [
                {"topic": ".*", "op": "receive"},
                {"topic": "/[^/]+/(goal_pose|initialpose)", "op": "send"},
            ],
        }
    )
    return {"version": 1, "identities": identities}


def client_config(robot: DemoRobot, ws_url: str) -> Any:
    """A robot's ``client.yaml`` (design.md section 5) as plain data."""
    return {
        "server_url": ws_url,
        "robot_name": robot.name,
        "bind_address": robot.address,
        "token_file": None,
        "publish": [
            {
                "topic": topic,
                "type": type_name,
                "priority": priority,
                "rate_limit_hz": rate,
                "no_drop": no_drop,
                "compression": compression,
                **MEDIA.get(topic, {}),
            }
            for topic, type_name, priority, rate, no_drop, compression in DEFAULT_PUBLISH
        ],
        "subscribe": [
            {
                "remote_topic": f"/{robot.name}/{topic}",
                "type": type_name,
                "local_topic": f"/{topic}",
            }
            for topic, type_name in DEFAULT_SUBSCRIBE
        ],
        "status": {"battery_topic": "/battery", "period_s": 1.0,
                   "location": "demo room (simulated, 10 x 8 m)"},
        # /tf throttled per frame pair, /tf_static latched (tf2_web_republisher's defaults).
        "tf": {},
    }


# What ``demo --record`` records (every robot topic) and its disk bounds: the demo's two
# robots write about 2 MB/s (mostly clouds), so files rotate every half minute and the
# directory stays under 1 GiB however long the demo runs.
RECORDING: dict[str, Any] = {
    "directory": "recordings",
    "rules": [{"topic": "/.*"}],
    "max_file_bytes": 64 * 1024 * 1024,
    "max_total_bytes": 1024 * 1024 * 1024,
}


def server_config(port: int, host: str, *, record: bool = False) -> Any:
    """The demo's ``server.yaml`` (design.md section 4) as plain data; with *record*, a
    ``recording:`` section (docs/server.md) into ``server/recordings``."""
    config: dict[str, Any] = {
        "listen_host": host,
        "listen_port": port,
        "auth_map": "auth.yaml",
        "database": "fleet.db",
        "no_drop_topics": [".*/events"],
    }
    if record:
        config["recording"] = dict(RECORDING)
    return config


def create_demo_fleet(
    root: Path, robot_count: int, *, port: int, base_domain_id: int, host: str = "127.0.0.1",
    record: bool = False,
) -> DemoFleet:
    """Write a demo fleet under *root* (created if missing).

    Args:
        root: directory for the fleet's files.
        robot_count: number of simulated robots (1 to 250).
        port: server port; 0 picks a free one.
        base_domain_id: ``ROS_DOMAIN_ID`` of the first robot; robot i gets base + i.
        host: loopback address the server listens on.
        record: the server records every robot topic into ``server/recordings``.

    Raises:
        ValueError: *robot_count* or the domain ids are out of range.
    """
    if not 1 <= robot_count <= 250:
        raise ValueError(f"robot count must be 1 to 250, got {robot_count}")
    if base_domain_id < 0 or base_domain_id + robot_count - 1 > MAX_ROS_DOMAIN_ID:
        raise ValueError(f"ROS domain ids {base_domain_id}..+{robot_count} are outside "
                         f"0-{MAX_ROS_DOMAIN_ID}")
    port = port or free_port(host)
    robots = tuple(
        DemoRobot(
            name=name,
            address=f"127.0.1.{i + 2}",
            ros_domain_id=base_domain_id + i,
            client_config=root / "robots" / name / "client.yaml",
        )
        for i, name in enumerate(robot_names(robot_count))
    )
    fleet = DemoFleet(
        root=root,
        server_config=root / "server" / "server.yaml",
        host=host,
        port=port,
        robots=robots,
        viewer_token=secrets.token_urlsafe(18),
        operator_token=secrets.token_urlsafe(18),
    )
    _write_yaml(fleet.server_config, server_config(port, host, record=record))
    _write_yaml(
        root / "server" / "auth.yaml", auth_map(robots, fleet.viewer_token, fleet.operator_token)
    )
    for robot in robots:
        _write_yaml(robot.client_config, client_config(robot, fleet.ws_url))
    return fleet


def _write_yaml(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    path.chmod(0o600)  # the auth map holds token hashes; keep every file private
