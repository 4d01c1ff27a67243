"""A goal dragged in the page arrives on the robot's *local ROS topic*: page -> relay ->
``fleetctl client`` (a real rclpy node) -> ``/goal_pose`` in the robot's ROS domain."""

from __future__ import annotations

import asyncio
import json
import math
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import load_auth_map
from fleetctl.server.config import ServerConfig
from fleetctl.wire.registry import TypeRegistry
from tests.webviz.conftest import webviz_server
from tests.webviz.demoproc import ros_process
from tests.webviz.fleet import OPERATOR_TOKEN, write_auth_map
from tests.webviz.test_browser import TIMEOUT_MS, drag_goal, sign_in

pytestmark = [pytest.mark.browser, pytest.mark.ros]

ROS_DOMAIN_ID = 47  # this module's share of the webviz range 40-59
GOAL_TYPE = "geometry_msgs/msg/PoseStamped"
DISCOVERY_TIMEOUT_S = 45.0


async def next_json(proc: asyncio.subprocess.Process, key: str, timeout_s: float) -> Any:
    """The next JSON line of *proc* that has *key* (bounded wait)."""
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    while True:
        line = await asyncio.wait_for(
            proc.stdout.readline(), max(0.01, deadline - time.monotonic())
        )
        if not line:
            raise AssertionError(f"process exited ({proc.returncode}) before printing {key!r}")
        obj = json.loads(line)
        if key in obj:
            return obj[key]


def client_yaml(path: Path, server_url: str) -> Path:
    path.write_text(
        yaml.safe_dump(
            {
                "server_url": server_url,
                "robot_name": "r1",
                "bind_address": "127.0.0.2",
                "publish": [],
                "subscribe": [
                    {
                        "remote_topic": "/r1/goal_pose",
                        "type": GOAL_TYPE,
                        "local_topic": "/goal_pose",
                    }
                ],
            }
        )
    )
    return path


async def test_goal_arrives_on_the_robots_local_ros_topic(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    auth = load_auth_map(write_auth_map(tmp_path / "auth.yaml", {"r1": "127.0.0.2"}))
    config = ServerConfig(
        listen_host="127.0.0.1",
        listen_port=0,
        auth_map=tmp_path / "auth.yaml",
        database=tmp_path / "fleet.db",
    )
    async with RelayServer(config, auth) as server:
        url = f"ws://127.0.0.1:{server.port}/"
        cfg = client_yaml(tmp_path / "client.yaml", url)
        async with (
            ros_process(ROS_DOMAIN_ID, "-m", "fleetctl.cli.main", "client", "--config", str(cfg)),
            ros_process(
                ROS_DOMAIN_ID,
                "-m", "tests.client.ros.rosproc", "listen", "/goal_pose", GOAL_TYPE
            ) as listener,
        ):
            assert await next_json(listener, "ready", DISCOVERY_TIMEOUT_S) is True
            web = webviz_server(url).start()
            webviz_factory.append(web)
            page = await browser.new_page(viewport={"width": 1400, "height": 1100})
            await sign_in(page, web.url, OPERATOR_TOKEN)
            row = page.locator('#robots tr[data-robot="r1"] td.state', has_text="online")
            await row.wait_for(timeout=TIMEOUT_MS)
            await page.click('#robots a[href="#/robot/r1"]')
            await page.locator("#tool-goal:not([disabled])").wait_for(timeout=TIMEOUT_MS)
            await drag_goal(page)
            cdr = bytes.fromhex(await next_json(listener, "cdr", 20))
    goal: Any = TypeRegistry.default().typestore.deserialize_cdr(cdr, GOAL_TYPE)
    assert goal.header.frame_id == "map"
    assert goal.pose.position.x == pytest.approx(4.0, abs=0.1)
    assert goal.pose.position.y == pytest.approx(0.0, abs=0.1)
    assert 2 * math.atan2(goal.pose.orientation.z, goal.pose.orientation.w) == pytest.approx(
        math.pi / 2, abs=0.05
    )
