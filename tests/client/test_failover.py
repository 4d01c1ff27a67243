"""A robot with several replicas' URLs fails over to a live one (issue 15).

Real relays (two RelayServer processes' worth, in this event loop), a real RobotLink and a
real WebSocket consumer; the replicas share no state here (that is NATS's job, tested in
tests/server/cluster/): what is tested is which replica the robot connects to, and that
its messages flow through the new one.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

from fleetctl.client.linktuning import LinkTuning
from fleetctl.client.transport import RobotLink
from fleetctl.server.app import RelayServer
from tests.client.conftest import Consumer, make_server, robot_config, running, wait_until
from tests.client.test_dialer import silent_port
from tests.support import string_frame

TUNING = LinkTuning(keepalive_interval_s=0.1, link_timeout_s=1.0, open_timeout_s=2.0,
                    failover_after_s=0.3)


def send(robot: RobotLink, text: str) -> None:
    robot.offer("/r1/events", string_frame("/r1/events", text, no_drop=True),
                priority=1.0, no_drop=True)


async def test_a_stopped_replica_hands_the_robot_to_the_next(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = make_server(tmp_path / "a")
    b = make_server(tmp_path / "b")
    async with b:
        await a.start()
        robot = RobotLink(robot_config([a.url, b.url], tmp_path), on_frame=lambda f: None,
                          tuning=TUNING)
        async with running(robot), Consumer.open(b.url, "/r1/.*") as on_b:
            await wait_until(lambda: robot.stats()["connected"])
            assert robot.stats()["server_url"] == a.url
            await a.stop()  # the replica's process stops: its port refuses
            await wait_until(lambda: robot.stats()["server_url"] == b.url
                             and robot.stats()["connected"])
            send(robot, "through b")
            await wait_until(lambda: "through b" in on_b.texts("/r1/events"))
            stats = robot.stats()
    assert stats["failovers"] == 1 and stats["connects"] == 2


async def test_a_silent_first_replica_is_passed_over_after_the_head_start(
        tmp_path: Path) -> None:
    async with make_server(tmp_path) as b:
        with silent_port() as silent:
            robot = RobotLink(robot_config([f"ws://127.0.0.1:{silent}/", b.url], tmp_path),
                              on_frame=lambda f: None, tuning=TUNING)
            async with running(robot), Consumer.open(b.url, "/r1/.*") as on_b:
                await wait_until(lambda: robot.stats()["connected"])
                send(robot, "hello")
                await wait_until(lambda: "hello" in on_b.texts("/r1/events"))
                stats = robot.stats()
                assert stats["server_url"] == b.url
    assert stats["failovers"] == 0  # its first connection: nothing to fail over from


async def test_a_replica_whose_handshake_fails_is_skipped(tmp_path: Path) -> None:
    """TCP connects but the upgrade fails (a half-dead process answering HTTP 503): the
    next attempt starts with the next replica."""

    async def unavailable(_: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\n\r\n")
        await writer.drain()
        writer.close()

    broken = await asyncio.start_server(unavailable, "127.0.0.1", 0)
    async with broken, make_server(tmp_path) as b:
        port = broken.sockets[0].getsockname()[1]
        robot = RobotLink(robot_config([f"ws://127.0.0.1:{port}/", b.url], tmp_path),
                          on_frame=lambda f: None, tuning=TUNING)
        async with running(robot):
            await wait_until(lambda: robot.stats()["connected"])
            stats = robot.stats()
            assert stats["server_url"] == b.url and stats["connect_failures"] >= 1


async def test_the_robot_stays_on_its_replica_after_a_reconnect(tmp_path: Path) -> None:
    """Both replicas up: a dropped connection comes back to the same replica (its
    session and mailbox are there), not to whichever answers first."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    async with make_server(tmp_path / "a") as a, make_server(tmp_path / "b") as b:
        robot = RobotLink(robot_config([b.url, a.url], tmp_path), on_frame=lambda f: None,
                          tuning=TUNING)
        async with running(robot):
            await wait_until(lambda: robot.stats()["connected"])
            first = robot.stats()["server_url"]
            for conn in list(_connections(b)):
                conn.transport.abort()  # the link resets
            await wait_until(lambda: robot.stats()["connects"] == 2
                             and robot.stats()["connected"])
            stats = robot.stats()
            assert first == b.url and stats["server_url"] == b.url
    assert stats["failovers"] == 0


def _connections(server: RelayServer) -> list[asyncio.WriteTransport]:
    assert server._server is not None
    return list(server._server.connections)  # type: ignore[arg-type]
