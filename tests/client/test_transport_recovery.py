"""The robot link on a dead path: the early switch, the false alarm, the outage's dials
and the stale rule (issue 19); the path readings themselves: test_tcppath.py."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest

from fleetctl.client import transport
from fleetctl.client.linktuning import LinkTuning
from fleetctl.client.tcppath import TcpInfo, read_tcp_info
from fleetctl.client.transport import RobotLink
from fleetctl.server.app import RelayServer
from tests.client.conftest import OPERATOR_TOKEN, robot_config, running, wait_until
from tests.support import decode_text, string_frame

# -- RobotLink: the early switch and the false alarm ----------------------------------------


class FakeKernel:
    """Stands in for ``read_tcp_info``: the real one until told the path is dead."""

    def __init__(self) -> None:
        self.dead = False
        self.polls = 0

    def __call__(self, sock: Any) -> TcpInfo | None:
        self.polls += 1
        if self.dead:
            return TcpInfo(unacked=5, last_ack_s=30.0, srtt_s=0.001)
        return read_tcp_info(sock)


TUNING = LinkTuning(keepalive_interval_s=0.1, link_timeout_s=30.0, open_timeout_s=2.0)


class EventsThroughTheRelay:
    """A robot sending no_drop events ``e<i>`` and a viewer (its own RobotLink, which
    drops resends) receiving them through the real relay."""

    def __init__(self, server: RelayServer, tmp_path: Path) -> None:
        self.got: list[str] = []
        (tmp_path / "op.token").write_text(OPERATOR_TOKEN + "\n")
        viewer_cfg = robot_config(server.url, tmp_path, robot_name="viewer", subscribe=[
            {"remote_topic": "/r1/events", "type": "std_msgs/msg/String"}],
            token_file="op.token")
        self.robot = RobotLink(robot_config(server.url, tmp_path), on_frame=lambda f: None,
                               tuning=TUNING)
        self.viewer = RobotLink(viewer_cfg,
                                on_frame=lambda f: self.got.append(decode_text(f)),
                                tuning=LinkTuning(open_timeout_s=2.0))

    @contextlib.asynccontextmanager
    async def running(self) -> AsyncIterator[None]:
        async with running(self.viewer), running(self.robot):
            await wait_until(lambda: self.robot.stats()["connected"]
                             and self.viewer.stats()["subscribed"] == ["/r1/events"])
            yield

    def offer(self, first: int, last: int) -> None:
        for i in range(first, last + 1):
            self.robot.offer("/r1/events", string_frame("/r1/events", f"e{i}", no_drop=True,
                                                        seq=i), priority=1.0, no_drop=True)


async def test_a_dead_path_switches_to_a_new_connection_exactly_once_in_order(
    server: RelayServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The kernel says the path is dead: the link dials, switches without waiting for the
    pong timeout, resends what was unacknowledged; the application receiving the events
    (through its own RobotLink, which drops resends) sees each once, in order."""
    kernel = FakeKernel()
    monkeypatch.setattr(transport, "read_tcp_info", kernel)
    events = EventsThroughTheRelay(server, tmp_path)
    async with events.running():
        events.offer(1, 10)
        kernel.dead = True
        events.offer(11, 20)  # some of these go out unacknowledged on the old connection
        await wait_until(lambda: events.robot.stats()["dead_paths"] == 1)
        kernel.dead = False
        events.offer(21, 30)
        await wait_until(lambda: "e30" in events.got)
        stats = events.robot.stats()
    assert events.got == [f"e{i}" for i in range(1, 31)]
    assert stats["connects"] == 2 and stats["link_timeouts"] == 0
    assert stats["last_close"] == "dead path"


async def test_a_path_dead_past_two_gaps_is_reset_and_redialled_exactly_once_in_order(
    server: RelayServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The early dial does not connect (the path is still down) and the old path stays
    silent past two gaps: the old connection is reset (not kept for a false alarm whose
    retransmission would deliver stale data), the link reconnects once the path is back,
    and the no_drop events still arrive once each, in order."""
    kernel = FakeKernel()
    monkeypatch.setattr(transport, "read_tcp_info", kernel)
    restored = asyncio.Event()
    real_dial = transport.dial_first

    async def dial_when_restored(*args: Any, **kw: Any) -> tuple[int, socket.socket]:
        await restored.wait()  # a silent path: no SYN-ACK until the restore
        return await real_dial(*args, **kw)

    events = EventsThroughTheRelay(server, tmp_path)
    robot = events.robot
    async with events.running():
        events.offer(1, 10)
        monkeypatch.setattr(transport, "dial_first", dial_when_restored)
        kernel.dead = True
        events.offer(11, 20)
        await wait_until(lambda: robot.stats()["stale_paths"] == 1
                         and not robot.stats()["connected"])  # reset, the dial waits
        kernel.dead = False
        restored.set()
        events.offer(21, 30)
        await wait_until(lambda: "e30" in events.got)
        stats = robot.stats()
    assert events.got == [f"e{i}" for i in range(1, 31)]
    assert stats["connects"] == 2 and stats["dead_paths"] == 0
    assert stats["link_timeouts"] == 0 and stats["last_close"] == "stale path"


class RobotOnItsOwnLoop:
    """A :class:`RobotLink` on its own thread and event loop, as in the robot's process,
    beside the test's loop that runs the relay: the robot's loop can be kept busy while
    the relay goes on answering."""

    def __init__(self, link: RobotLink) -> None:
        self.link = link
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self._thread.start()
        self._run = asyncio.run_coroutine_threadsafe(link.run(), self.loop)

    async def call(self, fn: Callable[[], Any]) -> Any:
        """*fn()* on the robot's loop; its result."""
        async def on_loop() -> Any:
            return fn()
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(on_loop(), self.loop))

    async def stop(self) -> None:
        await asyncio.wait_for(asyncio.wrap_future(
            asyncio.run_coroutine_threadsafe(self.link.stop(), self.loop)), 5.0)
        await asyncio.wait_for(asyncio.wrap_future(self._run), 5.0)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(5.0)
        self.loop.close()


async def test_a_busy_robot_does_not_take_its_live_path_for_dead(
    server: RelayServer, tmp_path: Path,
) -> None:
    """A busy host: the robot's process is off the CPU for 0.3 s right after it offered a
    message, so its watchdog wakes late, after the send loop wrote that message, and reads
    it in flight with the last ACK (of what the watchdog saw in flight before) 0.3 s old.
    The link stays (no early dial, no switch, no reset): what the earlier reading saw in
    flight was acknowledged. Before 2026-12-06 such episodes ended in a false alarm, a
    switch or a reset (a demo under load swapped to its standby about once a minute).

    The relay (this test's loop) is off the CPU too at the two readings that matter, as
    on a busy host, so that they see the data in flight: without its pong the relay's
    kernel delays its ACK (40 ms at least)."""
    # Keepalive pings only after 0.5 s idle (the default): the watchdog reads when the
    # episode's first message is written, not at a ping's.
    tuning = LinkTuning(link_timeout_s=30.0, open_timeout_s=2.0)
    robot = RobotOnItsOwnLoop(RobotLink(robot_config(server.url, tmp_path),
                                        on_frame=lambda f: None, tuning=tuning))

    def offer(i: int) -> None:
        robot.link.offer("/r1/events", string_frame("/r1/events", f"e{i}", no_drop=True,
                                                    seq=i), priority=1.0, no_drop=True)

    def off_the_cpu_after(i: int) -> None:
        offer(i)
        time.sleep(0.3)  # the robot's process descheduled (the stimulus, not a wait)

    def episode(i: int) -> None:
        offer(2 * i)  # written at once: the watchdog reads it in flight
        robot.loop.call_later(0.02, off_the_cpu_after, 2 * i + 1)

    try:
        await wait_until(lambda: robot.loop.is_running())
        stats: dict[str, Any] = {}
        while not stats.get("connected"):
            stats = await robot.call(robot.link.stats)
        for i in range(5):
            start = time.monotonic()
            robot.loop.call_soon_threadsafe(episode, i)
            time.sleep(0.01)  # the relay off the CPU while the first message is read
            await asyncio.sleep(start + 0.29 - time.monotonic())
            time.sleep(0.06)  # ... and while the robot wakes, writes and reads again
            await wait_until_acked(robot)
        stats = await robot.call(robot.link.stats)
    finally:
        await robot.stop()
    assert stats["dead_paths"] == stats["stale_paths"] == stats["false_alarms"] == 0, stats
    assert stats["connects"] == 1


async def wait_until_acked(robot: RobotOnItsOwnLoop) -> None:
    """Until the relay acknowledged every no_drop event offered (deadline 10 s)."""
    deadline = time.monotonic() + 10.0
    while (await robot.call(robot.link.stats))["no_drop_unacked"]:
        assert time.monotonic() < deadline
        await asyncio.sleep(0.01)  # the reading's pace, not a synchronization


async def test_a_false_alarm_keeps_the_connection_and_closes_the_new_socket(
    server: RelayServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The path looks dead, the early dial connects, but by then ACKs came again: the
    old connection stays (the server's session is not taken over)."""
    kernel = FakeKernel()
    monkeypatch.setattr(transport, "read_tcp_info", kernel)
    opened: list[socket.socket] = []
    real_dial = transport.dial_first

    async def slow_dial(*args: Any, **kw: Any) -> tuple[int, socket.socket]:
        won, sock = await real_dial(*args, **kw)
        kernel.dead = False  # the old path ACKs again before the new one is used
        opened.append(sock)
        return won, sock

    robot = RobotLink(robot_config(server.url, tmp_path), on_frame=lambda f: None,
                      tuning=TUNING)
    async with running(robot):
        # The standby's own dial must come first: patched, it would be the socket seen.
        await wait_until(lambda: robot.stats()["connected"]
                         and robot.stats()["standby"]["open"])
        monkeypatch.setattr(transport, "dial_first", slow_dial)
        robot.offer("/r1/events", string_frame("/r1/events", "x", no_drop=True, seq=1),
                    priority=1.0, no_drop=True)
        kernel.dead = True
        await wait_until(lambda: bool(opened) and opened[0].fileno() == -1)
        stats = robot.stats()
    assert stats["connects"] == 1 and stats["dead_paths"] == 0
    assert stats["false_alarms"] == 1


async def test_an_outage_dial_is_told_when_the_next_message_is_due(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The link's dial in an outage gets *ahead*: the seconds to the next message a topic
    is due to publish (past the window the attempt just started covers), on its publish
    times, not its offers (each offered 2.5 ms after its publish, as a scan is); a dial
    on a working path (the standby's) gets none."""
    link, now = _clocked_link(tmp_path)
    for i in range(5):  # /r1/pose published every 50 ms, the last at 100.2
        now[0] = 100.0025 + 0.05 * i
        _pose(link, f"p{i}", published_s=100.0 + 0.05 * i)
    given: list[Any] = []

    async def capture(*args: Any, **kw: Any) -> tuple[int, socket.socket]:
        given.append(kw.get("ahead"))
        return 0, socket.socket()

    monkeypatch.setattr(transport, "dial_first", capture)
    (await link._race([0], outage_age_s=0.5)).sock.close()
    (await link._race([0])).sock.close()
    off = RobotLink(robot_config("ws://127.0.0.1:9/", tmp_path,
                                 limits={"dial_ahead_of_messages": False}),
                    on_frame=lambda f: None)
    (await off._race([0], outage_age_s=0.5)).sock.close()
    ahead, standby, turned_off = given
    assert standby is None and turned_off is None
    spacing = link.tuning.dial.ahead_s
    assert spacing == 0.0015  # the default, which the figures below assume

    def starts_in(now_s: float) -> float:
        """When the dialer starts its next extra attempt, asked at *now_s* (its rule)."""
        now[0] = now_s
        return max(spacing, ahead() - spacing)

    # Two attempts lead the pose due at 100.25 (on its publishes, not its offers at
    # x.xx25): 3 ms and 1.5 ms before it; then the next pose, 100.30.
    assert starts_in(100.23) == pytest.approx(0.017)  # at 100.247
    assert starts_in(100.2471) == pytest.approx(0.0015)  # at 100.2486 (the loop was late)
    assert starts_in(100.2486) == pytest.approx(0.0484)  # at 100.297


async def test_on_a_long_round_trip_the_outage_dial_leads_by_more(tmp_path: Path) -> None:
    """With a 20 ms SYN round trip a SYN 3 ms before a publish is answered 17 ms after
    it (the message then goes as possibly stale): the two attempts lead by 1.5 and 3
    round trips, 30 and 60 ms."""
    link, now = _clocked_link(tmp_path)
    for i in range(5):  # published every 100 ms, the last at 100.4
        now[0] = 100.0 + 0.1 * i
        _pose(link, f"p{i}", published_s=now[0])
    link._syn_rtts.append(0.02)
    spacing = link.tuning.dial.ahead_s

    def target(now_s: float) -> float:
        now[0] = now_s
        return now_s + link._ahead_s() - spacing

    assert target(100.41) == pytest.approx(100.44)  # 60 ms before 100.5
    assert target(100.44) == pytest.approx(100.47)  # 30 ms before it
    assert target(100.47) == pytest.approx(100.54)  # 100.5 covered: 60 ms before 100.6
    link._syn_rtts.append(0.0005)  # a LAN: 3 and 1.5 ms
    assert target(100.47) == pytest.approx(100.497)


async def test_the_path_round_trip_is_the_least_of_the_last_dials(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """One SYN slowed by a busy host does not widen the next outage's leads: the path's
    round trip is the minimum over the last five dials' SYN round trips, measured on the
    dialled sockets."""
    link, _ = _clocked_link(tmp_path)
    rtts = iter([0.0007, 0.0029, 0.0008, 0.03, 0.03, 0.03, 0.03, 0.03])
    monkeypatch.setattr(transport, "read_tcp_info",
                        lambda sock: transport.TcpInfo(0, 0.0, next(rtts)))

    async def connected(*args: Any, **kw: Any) -> tuple[int, socket.socket]:
        return 0, socket.socket()

    monkeypatch.setattr(transport, "dial_first", connected)
    assert link._path_rtt_s == 0.0  # no dial yet
    seen = []
    for _ in range(8):
        (await link._dial()).sock.close()
        seen.append(link._path_rtt_s)
    # 0.7 ms holds through the busy 2.9 ms and while it is among the last five; a path
    # whose every SYN now takes 30 ms (a failover to LTE) is believed after five dials.
    assert seen == pytest.approx([0.0007, 0.0007, 0.0007, 0.0007, 0.0007, 0.0008, 0.0008,
                                  0.03])


def _clocked_link(tmp_path: Path) -> tuple[RobotLink, list[float]]:
    """A link on a settable clock; its wall clock reads the same seconds (as ns)."""
    now = [100.0]
    link = RobotLink(robot_config("ws://127.0.0.1:9/", tmp_path), on_frame=lambda f: None,
                     clock=lambda: now[0], wall_clock_ns=lambda: round(now[0] * 1e9))
    return link, now


def _pose(link: RobotLink, text: str, published_s: float | None = None) -> None:
    link.offer("/r1/pose", string_frame("/r1/pose", text), priority=1.0, no_drop=False,
               published_ns=0 if published_s is None else round(published_s * 1e9))


def _stale(link: RobotLink) -> int:
    return link.scheduler.stats()["topics"]["/r1/pose"]["dropped_stale"]  # type: ignore[index,no-any-return]


def test_after_an_outage_a_held_message_is_judged_by_its_publish_time(
    tmp_path: Path,
) -> None:
    """The dial returned at 100.010, the path's only proof. A pose offered at 100.012
    but published (its source timestamp) at 100.009 may have been published into the
    cut: dropped, though its offer came after the proof; one published at 100.011 is
    kept."""
    link, now = _clocked_link(tmp_path)
    for i, at in enumerate((99.90, 99.95, 100.0)):
        now[0] = at
        _pose(link, f"p{i}", at)
    now[0] = 100.012
    _pose(link, "late", 100.009)
    assert link.scheduler.drop_stale(now[0], after_outage=True, alive_since_s=100.010) == 1
    _pose(link, "fresh", 100.011)
    assert link.scheduler.drop_stale(now[0], after_outage=True, alive_since_s=100.010) == 0


def test_without_a_publish_time_a_held_message_counts_as_published_before_its_offer(
    tmp_path: Path,
) -> None:
    """A message the executor took has no source timestamp: it counts as published
    ``publish_to_offer_s`` (2 ms) before its offer; so does one whose source timestamp
    is in the future or older than ``max_publish_age_s`` (another host's clock)."""
    link, now = _clocked_link(tmp_path)
    assert link.tuning.publish_to_offer_s == 0.002
    for i, at in enumerate((99.90, 99.95, 100.0)):
        now[0] = at
        _pose(link, f"p{i}")
    for published in (None, 100.2, 90.0):  # unknown, in the future, 10 s old
        now[0] = 100.0115  # counts as published at 100.0095: before the proof
        _pose(link, "early", published)
        assert link.scheduler.drop_stale(now[0], after_outage=True,
                                         alive_since_s=100.010) == 1
        now[0] = 100.012  # counts as published at 100.010: kept
        _pose(link, "kept", published)
        assert link.scheduler.drop_stale(now[0], after_outage=True,
                                         alive_since_s=100.010) == 0


def test_after_a_reconnect_a_message_published_into_the_outage_is_dropped_at_its_offer(
    tmp_path: Path,
) -> None:
    """A pose published at 100.008, before the dial that ended the outage returned
    (100.010), reaches the offer at 100.013, after the new connection opened (a busy
    robot): it is stale, dropped and counted. One published at 100.011 goes; so does a
    no_drop message, whatever its age, and one without a publish time."""
    link, now = _clocked_link(tmp_path)
    for i, at in enumerate((99.90, 99.95)):
        now[0] = at
        _pose(link, f"p{i}", at)
    link._outage_since_s = 99.96
    now[0] = 100.011
    link._drop_stale(100.010)
    assert _stale(link) == 1  # p1, held through the outage
    now[0] = 100.013
    _pose(link, "into the cut", 100.008)
    assert _stale(link) == 2
    _pose(link, "unknown")
    assert _stale(link) == 2
    link.offer("/r1/events", string_frame("/r1/events", "e"), priority=1.0, no_drop=True,
               published_ns=round(100.008 * 1e9))
    _pose(link, "fresh", 100.011)
    assert _stale(link) == 2
    assert link.scheduler.stats()["topics"]["/r1/events"]["offered"] == 1  # type: ignore[index]
