"""RobotLink's standby connection through the real relay (issue 19).

The kernel's view of chosen sockets is faked (their path "dead"), as in
test_transport_recovery.py; everything else is real: the relay, the WebSocket
connections, the dial that shows the path works again.
"""

from __future__ import annotations

import logging
import socket
from pathlib import Path
from typing import Any

import pytest
from websockets.asyncio.server import ServerConnection, serve

from fleetctl.client import transport
from fleetctl.client.standby import KEEPALIVE_IDLE_S, KEEPALIVE_INTERVAL_S, KEEPALIVE_PROBES
from fleetctl.client.tcppath import TcpInfo, read_tcp_info
from fleetctl.client.transport import RobotLink
from fleetctl.server.app import RelayServer
from tests.client.conftest import robot_config, running, wait_until
from tests.client.test_transport_recovery import TUNING, EventsThroughTheRelay
from tests.support import string_frame


def local_port(sock: Any) -> int | None:
    try:
        return int(sock.getsockname()[1])
    except (OSError, AttributeError):
        return None


class DeadSockets:
    """``read_tcp_info`` that reports the sockets on chosen local ports as stuck (data
    unacknowledged, no ACK for 30 s); the others as they are."""

    def __init__(self) -> None:
        self.ports: set[int] = set()

    def __call__(self, sock: Any) -> TcpInfo | None:
        if local_port(sock) in self.ports:
            return TcpInfo(unacked=5, last_ack_s=30.0, srtt_s=0.001)
        return read_tcp_info(sock)

    def kill(self, link: RobotLink) -> None:
        """The path of *link*'s current connection goes silent."""
        self._kill(link._ws)

    def kill_standby(self, link: RobotLink) -> None:
        """The path of *link*'s standby connection goes silent."""
        assert link._standby is not None
        self._kill(link._standby.connection)

    def _kill(self, ws: Any) -> None:
        assert ws is not None
        port = local_port(ws.transport.get_extra_info("socket"))
        assert port is not None
        self.ports.add(port)


def through_the_relay(server: RelayServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                      ) -> tuple[DeadSockets, EventsThroughTheRelay]:
    """The robot and its viewer through the real relay, with the kernel's view faked."""
    kernel = DeadSockets()
    monkeypatch.setattr(transport, "read_tcp_info", kernel)
    return kernel, EventsThroughTheRelay(server, tmp_path)


def standby(link: RobotLink) -> dict[str, Any]:
    stats = link.stats()["standby"]
    assert isinstance(stats, dict)
    return stats


async def test_after_a_dead_path_the_standby_carries_on_exactly_once_in_order(
    server: RelayServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The robot keeps a standby beside its connection; when the path dies and a dial
    shows it works again, the standby is activated (no new upgrade): the server moves the
    session onto it, the no_drop events arrive once each, in order, and the socket that
    dial connected becomes the next standby."""
    caplog.set_level(logging.INFO)
    kernel, events = through_the_relay(server, tmp_path, monkeypatch)
    robot = events.robot
    async with events.running():
        await wait_until(lambda: standby(robot)["open"])
        events.offer(1, 10)
        await wait_until(lambda: "e10" in events.got)
        kernel.kill(robot)
        events.offer(11, 20)  # some go out unacknowledged on the dead connection
        await wait_until(lambda: standby(robot)["activations"] == 1)
        events.offer(21, 30)
        await wait_until(lambda: "e30" in events.got)
        await wait_until(lambda: standby(robot)["open"])  # the next one
        stats = robot.stats()
    assert events.got == [f"e{i}" for i in range(1, 31)]
    assert stats["connects"] == 2 and stats["dead_paths"] == 1
    assert stats["standby"]["opened"] == 2 and stats["standby"]["unusable"] == 0
    assert stats["identities"] == ["r1"]  # the welcome came again on activation
    log = caplog.text
    assert "activated its standby" in log and "standby activated in" in log
    # The session moved onto the standby: resumed (the dead connection's RST reached the
    # relay first, as on loopback) or taken over from it (a RST lost in a real cut).
    assert "resumed session r1/r1" in log or "takes session r1/r1" in log


async def test_a_standby_with_unacknowledged_data_is_not_used(
    server: RelayServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A standby whose own path looks stuck would wait for a retransmission too: it is
    closed, and the dialled socket gets a normal upgrade; nothing is lost."""
    kernel, events = through_the_relay(server, tmp_path, monkeypatch)
    robot = events.robot
    async with events.running():
        await wait_until(lambda: standby(robot)["open"])
        events.offer(1, 10)
        kernel.kill_standby(robot)
        kernel.kill(robot)
        events.offer(11, 20)
        await wait_until(lambda: robot.stats()["dead_paths"] == 1)
        events.offer(21, 30)
        await wait_until(lambda: "e30" in events.got)
        stats = robot.stats()
    assert events.got == [f"e{i}" for i in range(1, 31)]
    assert stats["standby"]["unusable"] == 1 and stats["standby"]["activations"] == 0
    assert stats["connects"] == 2


async def test_the_standby_opens_only_once_the_connection_works(
    server: RelayServer, tmp_path: Path,
) -> None:
    robot = RobotLink(robot_config(server.url, tmp_path), on_frame=lambda f: None,
                      tuning=TUNING)
    async with running(robot):
        await wait_until(lambda: standby(robot)["open"])
        assert robot.stats()["connected"]
        assert server.core.metrics.connections_open == 2  # the link and its standby
        assert robot._standby is not None and robot._standby.connection is not None
        sock = robot._standby.connection.transport.get_extra_info("socket")
        # Kept alive for NATs that forget idle mappings; the link's own socket is not.
        assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE) == 1
        assert [sock.getsockopt(socket.IPPROTO_TCP, opt) for opt in (
            socket.TCP_KEEPIDLE, socket.TCP_KEEPINTVL, socket.TCP_KEEPCNT)] == [
            KEEPALIVE_IDLE_S, KEEPALIVE_INTERVAL_S, KEEPALIVE_PROBES]
        assert robot._ws is not None
        main = robot._ws.transport.get_extra_info("socket")
        assert main.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE) == 0


async def test_a_server_that_does_not_offer_it_gets_no_standby(tmp_path: Path) -> None:
    """A Robofleet-convention server (plain websockets, no standby header) sees one
    connection, and the robot's frames on it, as before."""
    upgrades: list[dict[str, str]] = []
    frames: list[bytes] = []

    async def handler(ws: ServerConnection) -> None:
        assert ws.request is not None
        upgrades.append(dict(ws.request.headers.raw_items()))
        async for message in ws:
            if isinstance(message, bytes):
                frames.append(message)

    async with serve(handler, "127.0.0.1", 0) as plain:
        port = plain.sockets[0].getsockname()[1]
        robot = RobotLink(robot_config(f"ws://127.0.0.1:{port}/", tmp_path),
                          on_frame=lambda f: None, tuning=TUNING)
        async with running(robot):
            robot.offer("/r1/events", string_frame("/r1/events", "x", no_drop=True, seq=1),
                        priority=1.0, no_drop=True)
            await wait_until(lambda: any(b"/r1/events" in f for f in frames) and robot._acked_any)
            # The first pong is where a standby would be asked for, synchronously.
            assert robot._standby is not None and robot._standby._opener is None
            stats = robot.stats()
    assert len(upgrades) == 1 and "X-Fleetctl-Standby" not in upgrades[0]
    assert stats["standby"] == {"open": False, "opened": 0, "open_failures": 0,
                                "activations": 0, "lost": 0, "unusable": 0}
