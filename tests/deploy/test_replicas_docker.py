"""``fleetctl up --replicas 2`` on the real images with WireGuard on, as an operator runs it.

`init` -> `add-robot` -> `up --sim --replicas 2` -> the simulated robot is online and a
viewer signed in on replica 2 receives its topics (they cross NATS: the robot lists
replica 1 first), and relay-1 records it (fleet.yaml's recording, listed on the HTTPS ports)
-> `docker kill` replica 1 -> the robot fails over to replica 2, the
viewer keeps receiving without reconnecting, `status` still lists the robot online, relay-2
records it ->
`down --delete-data` removes every volume (replicas' databases, NATS stores).
"""

from __future__ import annotations

import asyncio
import json
import socket
import ssl
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from websockets.asyncio.client import connect

from fleetctl.client.config import load_client_config
from fleetctl.wire.control import encode_subscription
from fleetctl.wire.metadata import read_metadata
from tests.deploy.test_lifecycle_docker import (
    ONLINE_TIMEOUT_S,
    Operator,
    _free_port,
    _token_file,
    deployment,  # noqa: F401 (the fixture)
    online,
    wait_until,
)

pytestmark = [pytest.mark.docker, pytest.mark.ros, pytest.mark.slow]

FAILOVER_TIMEOUT_S = 15.0


def container(project: str, service: str) -> str:
    out = subprocess.run(["docker", "ps", "-q", "--filter",
                          f"label=com.docker.compose.project={project}", "--filter",
                          f"label=com.docker.compose.service={service}"],
                         capture_output=True, text=True, check=True).stdout.split()
    assert out, f"no running {service} container"
    return out[0]


async def watch(url: str, token: str, kill: Callable[[], None]) -> dict[str, float]:
    """Sign in on *url*, receive husky1's topics, call *kill* once they flow, and measure
    how long the flow stops; the connection must stay open throughout."""
    context = ssl.create_default_context()
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    async with connect(url, ssl=context, open_timeout=10, max_size=None,
                       additional_headers={"Authorization": f"Bearer {token}"}) as ws:
        while True:  # the welcome first
            first = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(first, str) and json.loads(first).get("type") == "welcome":
                break
        await ws.send(encode_subscription("/husky1/.*"))

        async def next_topic_frame(timeout_s: float) -> float:
            deadline = time.monotonic() + timeout_s
            while True:
                left = max(0.01, deadline - time.monotonic())
                frame = await asyncio.wait_for(ws.recv(), left)
                if isinstance(frame, bytes) and read_metadata(frame).topic.startswith(
                        "/husky1/"):
                    return time.monotonic()

        await next_topic_frame(ONLINE_TIMEOUT_S)
        killed = time.monotonic()
        await asyncio.get_running_loop().run_in_executor(None, kill)
        back = await next_topic_frame(FAILOVER_TIMEOUT_S)
        # Still flowing afterwards, on the same connection.
        for _ in range(5):
            await next_topic_frame(5.0)
        return {"gap_s": back - killed}


def test_a_robot_fails_over_between_replicas_deployed_by_up(
        deployment: tuple[Operator, Path, str]) -> None:  # noqa: F811
    op, fleet, project = deployment
    https, udp = _free_port(), _free_port(socket.SOCK_DGRAM)
    op.run("init", str(fleet), "--endpoint", f"127.0.0.1:{udp}")
    op.run("add-robot", "husky1")
    token = op.json("add-user", "alice@example.com", "--role", "viewer")["token"]
    fleet_yaml = fleet / "fleet.yaml"
    fleet_yaml.write_text(fleet_yaml.read_text() + 'recording:\n  topics: ["/.*/odom"]\n')
    op.run("render")
    recorder = _token_file(op, fleet, "rec@example.com")
    out = op.run("up", "--sim", "--wireguard", "on", "--replicas", "2", "--bind", "127.0.0.1",
                 "--https-port", str(https), "--project", project)
    assert "server_url: [ws://10.8.0.1:8080/, ws://10.8.0.1:8081/]" in out, out
    # Recorded in fleet.yaml: the robot's own client.yaml (its exported bundle) lists both.
    assert "relay_replicas: 2" in (fleet / "fleet.yaml").read_text()
    robot_config = load_client_config(fleet / "robots/husky1/client.yaml")
    assert robot_config.server_urls == ("ws://10.8.0.1:8080/", "ws://10.8.0.1:8081/")
    took = wait_until("husky1 online", lambda: online(op, {"husky1"}), ONLINE_TIMEOUT_S * 3)
    print(f"husky1 online {took:.1f} s after `up --replicas 2` returned")
    services = {s["service"]: s for s in op.json("status")["services"]}
    assert {"server", "relay-1", "relay-2", "nats-1", "nats-2", "nats-3",
            "robot-husky1"} <= set(services)
    # Each replica records what its own senders sent, into its own volume, and serves it
    # on its own HTTPS port: husky1 is on relay-1 (listed first in its client.yaml).
    def listing(*ports: int) -> list[str]:
        servers = [arg for port in ports for arg in ("--server", f"https://127.0.0.1:{port}/")]
        return ["recordings", "list", *servers, "--token-file", str(recorder),
                "--ca-file", str(fleet / "server" / "tls" / "cert.pem")]

    wait_until("husky1's odometry recorded by relay-1",
               lambda: any(r["name"].startswith("fleet_relay-1_") and "/husky1/odom"
                           in r["topics"] for r in op.json(*listing(https, https + 1))),
               ONLINE_TIMEOUT_S)
    assert op.json("status")["recordings"]["files"] >= 1  # asked of every replica
    relay1 = container(project, "relay-1")

    def kill() -> None:
        subprocess.run(["docker", "kill", relay1], capture_output=True, check=True)

    figures = asyncio.run(watch(f"wss://127.0.0.1:{https + 1}/", token, kill))
    print(f"relay-1 killed: husky1's topics back on relay-2 after {figures['gap_s']:.2f} s")
    assert figures["gap_s"] < FAILOVER_TIMEOUT_S
    wait_until("husky1 online through relay-2", lambda: online(op, {"husky1"}),
               ONLINE_TIMEOUT_S)
    wait_until("husky1's odometry recorded by relay-2 after the failover",
               lambda: any(r["name"].startswith("fleet_relay-2_") and "/husky1/odom"
                           in r["topics"] for r in op.json(*listing(https + 1))),
               ONLINE_TIMEOUT_S)
    # The robot's session and the no_drop stream work under up's NATS permissions.
    logs = subprocess.run(["docker", "logs", container(project, "relay-2")],
                          capture_output=True, text=True, check=True)
    text = logs.stdout + logs.stderr
    for trouble in ("Permissions Violation", "cannot read the sessions' stream",
                    "cannot store no_drop frames", "cannot write the"):
        assert trouble not in text, text[-3000:]
    op.run("down", "--delete-data")
    volumes = subprocess.run(["docker", "volume", "ls", "-q", "--filter",
                              f"name={project}_"], capture_output=True, text=True,
                             check=True).stdout.split()
    assert volumes == []
