"""A topic of the fleet's own message type through a real relay: the relay routes frames by
topic and needs no definition; a consumer with the fleet's definitions decodes them; the
server's parts that would need the definition (Foxglove channels) say so in the log and
keep running (docs/operator.md, "The fleet's own message types")."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from fleetctl.deploy.msgtypes import load_msg_types
from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerConfig
from fleetctl.wire.codec import Codec
from fleetctl.wire.registry import TypeRegistry
from tests.deploy.test_msgtypes import write_own_packages
from tests.server.conftest import (
    BOB_TOKEN,
    auth_map,
    client,
    next_binary,
    next_json,
    subscribe,
    wait_for,
)

STATUS = "my_robot_msgs/msg/Status"


def _fleet_codec(fleet_dir: Path) -> Codec:
    """What a robot with the package installed encodes with (and a consumer that has it)."""
    registry = TypeRegistry.default()
    registry.add_msg_texts(dict(load_msg_types(fleet_dir).texts))
    return Codec(registry)


def _relay(tmp_path: Path) -> RelayServer:
    """A real relay on 127.0.0.1:0 with the server tests' identities (husky1 at 127.0.0.2)."""
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0,
                          auth_map=tmp_path / "auth.yaml", database=tmp_path / "fleet.db")
    return RelayServer(config, auth_map())


async def test_an_own_type_is_relayed_and_decodes_with_the_fleets_definitions(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    write_own_packages(tmp_path)
    codec = _fleet_codec(tmp_path)
    store = codec.registry.typestore
    msg = store.types[STATUS](
        header=store.types["std_msgs/msg/Header"](
            stamp=store.types["builtin_interfaces/msg/Time"](sec=7, nanosec=9), frame_id="base"),
        mode=1, battery=store.types["my_robot_msgs/msg/Battery"](voltage_v=24.5,
                                                                  charge_ratio=0.75),
        motor_temperatures_c=[40.0, 41.5], note="ok")
    frame = codec.encode(msg, STATUS, "/husky1/robot_status")
    caplog.set_level(logging.WARNING, logger="fleetctl")
    async with _relay(tmp_path) as server, client(server, source="127.0.0.2") as robot, \
            client(server, token=BOB_TOKEN) as bob:
        await next_json(robot, "welcome")
        assert (await subscribe(bob, "/husky1/robot_status"))["type"] == "subscribed"
        await robot.send(frame)
        received = await next_binary(bob)
        meta, decoded = codec.decode(received)
        assert (meta.topic, meta.type) == ("/husky1/robot_status", STATUS)
        assert (decoded.battery.voltage_v, list(decoded.motor_temperatures_c)) == (
            24.5, [40.0, 41.5])
        assert decoded.header.frame_id == "base" and decoded.note == "ok"
        # The Foxglove catalog (default registry) offers no channel for it, and says why.
        await wait_for(lambda: f"no Foxglove channel for type {STATUS}" in caplog.text)
        assert server.foxglove.catalog.refused == 1
