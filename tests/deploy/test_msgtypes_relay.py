"""A topic of the fleet's own message type through a real relay, its server.yaml rendered
from a fleet directory with msg_types/: the relay routes it by topic, the web listener
serves its layout, a Foxglove viewer gets a channel and CDR that rosbags decodes with the
definitions alone. A server without the definitions says so in the log and keeps running
(docs/operator.md, "The fleet's own message types")."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import pytest
import yaml
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.msg import get_types_from_msg

from fleetctl.deploy import compose
from fleetctl.deploy import operations as ops
from fleetctl.deploy.msgtypes import load_msg_types
from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerConfig, WebConfig, load_server_config
from fleetctl.server.msgtypes import MsgTypes, codec_for, parse_msg_types
from fleetctl.wire.codec import Codec
from tests.deploy.conftest import SeededKeySource
from tests.deploy.test_msgtypes import write_own_packages
from tests.server.certs import self_signed
from tests.server.conftest import (
    ALICE_TOKEN,
    BOB_TOKEN,
    auth_map,
    client,
    next_binary,
    next_json,
    subscribe,
    wait_for,
)
from tests.server.foxglove.fxclient import Viewer, https_get, open_viewer, ticket

STATUS = "my_robot_msgs/msg/Status"
TOPIC = "/husky1/robot_status"


def _rendered_msg_types(root: Path) -> MsgTypes:
    """init, add-robot, the fleet's own packages, render: server.yaml's msg_types."""
    fleet_dir = root / "fleet"
    keys = SeededKeySource()
    ops.create_fleet(fleet_dir, endpoint="vpn.example.com:51820", keys=keys)
    ops.add_robot(fleet_dir, "husky1", keys=keys)
    write_own_packages(fleet_dir)
    ops.render_fleet(fleet_dir)
    msg_types = load_server_config(fleet_dir / "server" / "server.yaml").msg_types
    assert msg_types == load_msg_types(fleet_dir).texts  # every byte through the YAML
    return msg_types


def _relay(root: Path, msg_types: MsgTypes) -> RelayServer:
    """A real relay on 127.0.0.1:0 with its TLS web listener and the server tests'
    identities (husky1 at 127.0.0.2, alice may receive everything)."""
    cert, key = self_signed(root / "tls")
    (root / "vendor").mkdir(exist_ok=True)
    web = WebConfig(tls_cert=cert, tls_key=key, listen_host="127.0.0.1", listen_port=0,
                    vendor_dir=root / "vendor")
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=root / "auth.yaml",
                          database=root / "fleet.db", web=web, msg_types=msg_types)
    return RelayServer(config, auth_map())


def _status(codec: Codec, mode: int) -> bytes:
    """The frame a robot with the package installed sends."""
    t = codec.registry.typestore.types
    msg = t[STATUS](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=7, nanosec=9),
                                        frame_id="base"),
        mode=mode, battery=t["my_robot_msgs/msg/Battery"](voltage_v=24.5, charge_ratio=0.75),
        motor_temperatures_c=[40.0, 41.5], note="ok")
    return codec.encode(msg, STATUS, TOPIC, seq=mode)


def _reference(msg_types: MsgTypes) -> Any:
    """rosbags' own Jazzy store plus the definitions: decodes CDR without fleetctl."""
    store = get_typestore(Stores.ROS2_JAZZY)
    for name, text in msg_types:
        store.register(get_types_from_msg(text, name))
    return store


async def test_an_own_type_is_relayed_shown_and_offered_to_foxglove(tmp_path: Path) -> None:
    msg_types = _rendered_msg_types(tmp_path)
    assert {name for name, _ in msg_types} == {
        STATUS, "my_robot_msgs/msg/Battery", "base_msgs/msg/Mission"}
    codec = codec_for(msg_types)
    async with _relay(tmp_path, msg_types) as server, \
            client(server, source="127.0.0.2") as robot, client(server, token=BOB_TOKEN) as bob:
        await next_json(robot, "welcome")
        assert (await subscribe(bob, TOPIC))["type"] == "subscribed"
        await robot.send(_status(codec, 1))
        meta, decoded = codec.decode(await next_binary(bob))
        assert (meta.topic, meta.type, decoded.battery.voltage_v) == (TOPIC, STATUS, 24.5)

        status, body = await https_get(server.web_port, f"/types/{STATUS}.json")
        assert status == 200
        assert "battery" in [f["name"] for f in json.loads(body)["tables"][STATUS]["fields"]]

        await wait_for(lambda: bool(server.foxglove.catalog.channels()))
        async with open_viewer(server.web_port,
                               await ticket(server.web_port, ALICE_TOKEN)) as ws:
            viewer = Viewer(ws)
            await viewer.until(lambda: viewer.channel(TOPIC) is not None)
            channel = viewer.channel(TOPIC)
            assert channel is not None and channel["schemaName"] == STATUS
            await viewer.subscribe(3, channel["id"])
            await wait_for(lambda: len(server.core.subs.receivers(TOPIC)) == 2)
            await robot.send(_status(codec, 2))
            await viewer.until(lambda: len(viewer.messages) == 1)
            got = _reference(msg_types).deserialize_cdr(viewer.messages[0][2], STATUS)
            assert (got.mode, got.battery.charge_ratio, got.note) == (2, 0.75, "ok")
            assert list(got.motor_temperatures_c) == [40.0, 41.5]


async def test_a_server_without_the_definitions_says_so_and_keeps_relaying(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    codec = codec_for(_rendered_msg_types(tmp_path))
    caplog.set_level(logging.WARNING, logger="fleetctl")
    async with _relay(tmp_path, ()) as server, \
            client(server, source="127.0.0.2") as robot, client(server, token=BOB_TOKEN) as bob:
        await next_json(robot, "welcome")
        assert (await subscribe(bob, TOPIC))["type"] == "subscribed"
        await robot.send(_status(codec, 1))
        assert codec.decode(await next_binary(bob))[0].type == STATUS
        await wait_for(lambda: f"no Foxglove channel for type {STATUS}" in caplog.text)
        assert server.foxglove.catalog.refused == 1
        status, _ = await https_get(server.web_port, f"/types/{STATUS}.json")
        assert status == 404


def test_the_container_server_yaml_of_fleetctl_up_carries_them(tmp_path: Path) -> None:
    # `fleetctl up` runs the server on a copy of server.yaml with container paths.
    msg_types = _rendered_msg_types(tmp_path)
    text = compose.server_config_text(compose.plan_for(tmp_path / "fleet"))
    assert parse_msg_types(yaml.safe_load(text)["msg_types"], Path("server.yaml")) == msg_types
