"""Latched topics end to end: real rclpy processes, a real server, two real robot clients.

On robot ``alpha`` (domain 26) a map_server-like process publishes ``/map`` (147 KB,
TRANSIENT_LOCAL, depth 1) and, when tf2_msgs is installed, a static broadcaster publishes
``/tf_static``, both *before* alpha's client starts. Robot ``bravo`` (domain 27) starts
after the server has the map; a ROS node started on bravo after that, and a plain
WebSocket viewer connecting last, both get the map (and the static transforms).
"""

from __future__ import annotations

import asyncio
import hashlib
import importlib.util
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")

from fleetctl.demo.fleet import free_port
from fleetctl.demo.run import http_ok, online_robots
from fleetctl.waiting import wait_until
from fleetctl.wire.codec import Codec
from fleetctl.wire.compression import COMPRESSED_TYPE, decompress
from fleetctl.wire.metadata import read_metadata
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.samples import occupancy_grid
from fleetctl.wire.whole_messages import first_whole_messages
from tests.client.ros.harness import JsonProc, fleetctl_argv, ros_helper, write_yaml

pytestmark = [pytest.mark.ros, pytest.mark.slow]
ALPHA_DOMAIN, BRAVO_DOMAIN = 26, 27  # this file's own domains (the client tests use 20-39)
ALPHA_IP, BRAVO_IP = "127.0.1.6", "127.0.1.7"
OPERATOR_TOKEN = "operator-token-for-latched-tests"
STARTUP_S = 30.0
MAP_TYPE = "nav_msgs/msg/OccupancyGrid"
TF_TYPE = "tf2_msgs/msg/TFMessage"
HAVE_TF2_MSGS = importlib.util.find_spec("tf2_msgs") is not None
STATIC_CHILDREN = ("laser", "camera_link", "imu_link")


@dataclass
class Fleet:
    root: Path
    port: int
    map_cdr: bytes
    procs: dict[str, JsonProc] = field(default_factory=dict)

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/"

    def start(self, name: str, proc: JsonProc) -> JsonProc:
        self.procs[name] = proc
        return proc


def _configs(root: Path, port: int) -> None:
    write_yaml(root / "server.yaml", {"listen_host": "127.0.0.1", "listen_port": port,
                                      "auth_map": "auth.yaml", "database": "fleet.db"})
    write_yaml(root / "auth.yaml", {"version": 1, "identities": [
        {"name": "alpha", "ip": ALPHA_IP, "rules": [{"topic": "/alpha/.*", "op": "send"}]},
        {"name": "bravo", "ip": BRAVO_IP, "rules": [
            {"topic": "/bravo/.*", "op": "send"},
            {"topic": "/alpha/(map|tf_static)", "op": "receive"}]},
        {"name": "operator",
         "token_sha256": hashlib.sha256(OPERATOR_TOKEN.encode()).hexdigest(),
         "rules": [{"topic": ".*", "op": "receive"}]},
    ]})
    fast = {"reconnect_min_s": 0.1, "reconnect_max_s": 0.5}
    write_yaml(root / "alpha.yaml", {
        "server_url": f"ws://127.0.0.1:{port}/", "robot_name": "alpha",
        "bind_address": ALPHA_IP,
        "publish": [{"topic": "/map", "type": MAP_TYPE}],  # compression none: the client
        "tf": {},                                           # deflates it (latched, > 64 KiB)
        "limits": fast})
    subscribe = [{"remote_topic": "/alpha/map", "type": MAP_TYPE, "local_topic": "/alpha_map"}]
    if HAVE_TF2_MSGS:
        subscribe.append({"remote_topic": "/alpha/tf_static", "type": TF_TYPE,
                          "local_topic": "/alpha_tf_static"})
    write_yaml(root / "bravo.yaml", {
        "server_url": f"ws://127.0.0.1:{port}/", "robot_name": "bravo",
        "bind_address": BRAVO_IP, "subscribe": subscribe, "limits": fast})


def _static_cdr(registry: TypeRegistry) -> bytes:
    get = registry.get
    transforms = [
        get("geometry_msgs/msg/TransformStamped").cls(
            get("std_msgs/msg/Header").cls(get("builtin_interfaces/msg/Time").cls(0, 0),
                                           "base_link"),
            child,
            get("geometry_msgs/msg/Transform").cls(
                get("geometry_msgs/msg/Vector3").cls(0.1 * (i + 1), 0.0, 0.3),
                get("geometry_msgs/msg/Quaternion").cls(0.0, 0.0, math.sin(0.25),
                                                        math.cos(0.25))))
        for i, child in enumerate(STATIC_CHILDREN)]
    return bytes(registry.typestore.serialize_cdr(get(TF_TYPE).cls(transforms), TF_TYPE))


async def _viewer_frames(url: str, topics: list[str], count: int) -> list[bytes]:
    """Connect as a plain viewer, subscribe *topics*, return the first *count* whole frames
    (fragments reassembled)."""
    from websockets.asyncio.client import connect

    from fleetctl.wire.control import encode_subscription

    async with connect(url, additional_headers={"Authorization": f"Bearer {OPERATOR_TOKEN}"},
                       ping_interval=None, max_size=None) as ws:
        for topic in topics:
            await ws.send(encode_subscription(topic))
        return await first_whole_messages(ws, count)


def viewer_frames(fleet: Fleet, topics: list[str], count: int) -> list[bytes]:
    return asyncio.run(asyncio.wait_for(_viewer_frames(fleet.url, topics, count), STARTUP_S))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    root = tmp_path_factory.mktemp("latched")
    port = free_port()
    _configs(root, port)
    registry = TypeRegistry.default()
    map_cdr = bytes(registry.typestore.serialize_cdr(occupancy_grid(registry, 384), MAP_TYPE))
    (root / "map.cdr").write_bytes(map_cdr)
    fleet = Fleet(root, port, map_cdr)
    try:
        fleet.start("server", JsonProc(fleetctl_argv("server", "--config",
                                                     str(root / "server.yaml")),
                                       {}, root / "server.log"))
        wait_until(lambda: http_ok(f"http://127.0.0.1:{port}/healthz"), STARTUP_S,
                   describe="server")
        # The map (and static TF) exist before alpha's client does.
        fleet.start("map_server", ros_helper("latch", ["/map", MAP_TYPE, f"@{root / 'map.cdr'}"],
                                             ALPHA_DOMAIN, root / "map_server.log")
                    ).wait_for(lambda line: line.get("published", False), STARTUP_S, "map")
        if HAVE_TF2_MSGS:
            (root / "static.cdr").write_bytes(_static_cdr(registry))
            fleet.start("static_tf", ros_helper(
                "latch", ["/tf_static", TF_TYPE, f"@{root / 'static.cdr'}"], ALPHA_DOMAIN,
                root / "static_tf.log")
            ).wait_for(lambda line: line.get("published", False), STARTUP_S, "static tf")
        fleet.start("alpha", JsonProc(fleetctl_argv("client", "--config",
                                                    str(root / "alpha.yaml")),
                                      {"ROS_DOMAIN_ID": str(ALPHA_DOMAIN)}, root / "alpha.log"))
        # The server has the map once a viewer gets it: only then does bravo start.
        viewer_frames(fleet, ["/alpha/map"], 1)
        fleet.start("bravo", JsonProc(fleetctl_argv("client", "--config",
                                                    str(root / "bravo.yaml")),
                                      {"ROS_DOMAIN_ID": str(BRAVO_DOMAIN)}, root / "bravo.log"))
        wait_until(lambda: online_robots(f"http://127.0.0.1:{port}") >= {"alpha", "bravo"},
                   STARTUP_S, describe="both robots online")
        yield fleet
    finally:
        for proc in reversed(list(fleet.procs.values())):
            proc.stop()


def _late_listener(fleet: Fleet, topic: str, type_name: str, tag: str) -> dict[str, Any]:
    """A node started on bravo once the republished topic's publisher is transient-local
    subscribes only then, and still gets the message: the first line it prints."""
    listener = ros_helper("listen-latched", [topic, type_name], BRAVO_DOMAIN,
                          fleet.root / f"{tag}.log")
    try:
        listener.wait_for(lambda line: line.get("ready", False), STARTUP_S,
                          f"a transient-local publisher of {topic} on bravo")
        return listener.wait_for(lambda line: "cdr" in line, STARTUP_S, f"{topic} on bravo")
    finally:
        listener.stop()


def test_map_reaches_a_late_node_on_another_robot(fleet: Fleet) -> None:
    from nav_msgs.msg import OccupancyGrid
    from rclpy.serialization import deserialize_message

    line = _late_listener(fleet, "/alpha_map", MAP_TYPE, "late-map-node")
    received = deserialize_message(bytes.fromhex(line["cdr"]), OccupancyGrid)
    assert received == deserialize_message(fleet.map_cdr, OccupancyGrid)


def test_a_late_viewer_gets_the_map_compressed_and_latched(fleet: Fleet) -> None:
    (frame,) = viewer_frames(fleet, ["/alpha/map"], 1)
    meta = read_metadata(frame)
    assert (meta.type, meta.topic, meta.latched) == (COMPRESSED_TYPE, "/alpha/map", True)
    assert len(frame) < len(fleet.map_cdr) / 10  # 147 KB of map, deflated
    inner = decompress(frame, 1 << 24)
    codec = Codec(TypeRegistry.default())
    inner_meta, grid = codec.decode(inner)
    assert (inner_meta.type, inner_meta.latched, grid.info.width) == (MAP_TYPE, True, 384)


@pytest.mark.skipif(not HAVE_TF2_MSGS, reason="needs tf2_msgs (scripts/ros_msgs.sh)")
def test_tf_static_reaches_a_late_node_and_a_late_viewer(fleet: Fleet) -> None:
    codec = Codec(TypeRegistry.default())
    line = _late_listener(fleet, "/alpha_tf_static", TF_TYPE, "late-tf-node")
    msg = codec.registry.typestore.deserialize_cdr(bytes.fromhex(line["cdr"]), TF_TYPE)
    assert sorted(t.child_frame_id for t in msg.transforms) == sorted(STATIC_CHILDREN)
    (frame,) = viewer_frames(fleet, ["/alpha/tf_static"], 1)
    meta, whole = codec.decode(frame)
    assert meta.latched and meta.type == TF_TYPE
    assert sorted(t.child_frame_id for t in whole.transforms) == sorted(STATIC_CHILDREN)


def _map_to_odom_cdr(registry: TypeRegistry) -> bytes:
    get = registry.get
    identity = get("geometry_msgs/msg/TransformStamped").cls(
        get("std_msgs/msg/Header").cls(get("builtin_interfaces/msg/Time").cls(0, 0), "map"),
        "odom",
        get("geometry_msgs/msg/Transform").cls(get("geometry_msgs/msg/Vector3").cls(0, 0, 0),
                                               get("geometry_msgs/msg/Quaternion").cls(0, 0, 0,
                                                                                       1)))
    return bytes(registry.typestore.serialize_cdr(get(TF_TYPE).cls([identity]), TF_TYPE))


@pytest.mark.skipif(not HAVE_TF2_MSGS, reason="needs tf2_msgs (scripts/ros_msgs.sh)")
def test_a_transform_that_never_moves_reaches_viewers_who_come_later(fleet: Fleet) -> None:
    # A localizer publishing a constant map -> odom at 20 Hz: the robot's throttle sends it
    # once; viewers who subscribe after that get it from the relay's latched snapshot.
    codec = Codec(codec_registry := TypeRegistry.default())
    (fleet.root / "map_odom.cdr").write_bytes(_map_to_odom_cdr(codec_registry))
    fleet.start("localizer", ros_helper(
        "publish", ["/tf", TF_TYPE, f"@{fleet.root / 'map_odom.cdr'}", "20"], ALPHA_DOMAIN,
        fleet.root / "localizer.log")
    ).wait_for(lambda line: line.get("ready", False), STARTUP_S, "alpha's client on /tf")
    for _ in range(2):  # the second surely comes after map -> odom was last sent live
        (frame,) = viewer_frames(fleet, ["/alpha/tf"], 1)
        meta, msg = codec.decode(frame)
        assert (meta.type, meta.topic) == (TF_TYPE, "/alpha/tf")
        assert [(t.header.frame_id, t.child_frame_id) for t in msg.transforms] == [
            ("map", "odom")]
    assert meta.latched
