"""The dialer's pace in an outage (issue 19): fast when it begins, bounded while it lasts."""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket
from collections.abc import Iterator
from typing import Any

import pytest

from fleetctl.client.dialer import DialSettings, DialTimeout, dial, dial_first
from fleetctl.deploy.shaping import LinkShaper, detect
from tests.client.conftest import wait_until
from tests.netns import NEEDS_ROOT, SINK_TCP_PORT, Link, host_run
from tests.support import virtual_time


def test_stagger_is_flat_for_a_minute_then_slows() -> None:
    s = DialSettings()
    assert s.stagger_at(0.0) == s.stagger_at(5.0) == 0.01  # the e2e dropout's 5 s cut
    assert s.stagger_at(30.0) == s.outage_stagger_s == 0.01  # the e2e peer's 30 s cuts
    assert s.stagger_at(59.9) == 0.01
    assert s.stagger_at(60.0) == s.stagger_s == 0.25  # past a minute: the slow pace
    assert s.stagger_at(math.inf) == s.stagger_s  # not in an outage: the slow pace


def test_a_slower_outage_pace_doubles_up_to_it() -> None:
    s = DialSettings(outage_stagger_s=0.04)
    assert s.stagger_at(0.0) == pytest.approx(0.01)
    assert s.stagger_at(8.0) == pytest.approx(0.02)
    assert s.stagger_at(16.0) == pytest.approx(0.04)
    assert s.stagger_at(30.0) == 0.04


def test_outage_pace_never_slower_than_the_slow_pace() -> None:
    s = DialSettings(stagger_s=0.03, outage_stagger_s=0.04)
    assert s.stagger_at(30.0) == 0.03


def syns_per_second(s: DialSettings, age_s: float) -> float:
    """The cost bound of the module docstring: extra short attempts (one SYN each) at
    the outage's pace, long ones (two SYNs: Linux resends at 1 s) at the slow pace."""
    fast = 1 / s.stagger_at(age_s)
    return fast - 1 / s.stagger_s + 2 / s.stagger_s


def test_documented_cost_bound() -> None:
    s = DialSettings()
    assert syns_per_second(s, 0.0) == pytest.approx(104.0)
    assert syns_per_second(s, 30.0) == pytest.approx(104.0)
    assert syns_per_second(s, 60.0) == pytest.approx(8.0)
    # ~130 bytes a SYN inside WireGuard: 13.5 KB/s, ~810 KB over the first minute.
    assert syns_per_second(s, 0.0) * 130 * 60 == pytest.approx(811_200)


@contextlib.contextmanager
def attempts_on_virtual_time(monkeypatch: pytest.MonkeyPatch,
                             connects: Any) -> Iterator[asyncio.AbstractEventLoop]:
    """The running loop on virtual time, its ``sock_connect`` replaced by *connects* and
    its ``getaddrinfo`` answering at once; yields the loop.

    Why: these tests count the attempts a dial starts in a few tenths of a second at a
    10 ms pace. On a loaded host the real loop wakes late and starts fewer (9 where 10
    were asserted, once in 30 runs at load 10); on virtual time every timer fires when
    scheduled, so what is counted is the dialer's schedule, exactly."""
    loop = asyncio.get_running_loop()
    monkeypatch.setattr(loop, "sock_connect", connects)
    monkeypatch.setattr(loop, "getaddrinfo", resolved_at_once)
    with virtual_time(loop):
        yield loop


class HangingConnects:
    """``sock_connect`` that never completes (a silent path); counts attempts and their
    cancellations, and closes nothing itself (the dialer does)."""

    def __init__(self) -> None:
        self.started = 0
        self.cancelled = 0
        self.most_at_once = 0

    async def __call__(self, sock: socket.socket, address: Any) -> None:
        self.started += 1
        self.most_at_once = max(self.most_at_once, self.started - self.cancelled)
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            self.cancelled += 1
            raise


@pytest.mark.parametrize(("age_s", "low", "high"), [(0.0, 49, 51), (math.inf, 2, 3)])
async def test_attempts_follow_the_outage_pace_and_a_timeout_is_a_dial_timeout(
    monkeypatch: pytest.MonkeyPatch, age_s: float, low: int, high: int,
) -> None:
    hanging = HangingConnects()
    with attempts_on_virtual_time(monkeypatch, hanging), pytest.raises(DialTimeout):
        await dial("127.0.0.1", 9, timeout_s=0.5, outage_age_s=age_s)
    # 0.5 s at 10 ms is 50 attempts, at 250 ms 2 or 3.
    assert low <= hanging.started <= high, hanging.started
    assert hanging.cancelled == hanging.started  # every attempt closed at the end
    assert isinstance(DialTimeout("x"), TimeoutError)  # callers catching TimeoutError


async def test_short_attempts_expire_before_the_kernel_resends_their_syn(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With the fast pace, at most the attempts of ``short_life_s`` plus the long ones of
    ``attempt_life_s`` are open at once: old short ones were abandoned."""
    hanging = HangingConnects()
    settings = DialSettings(fast_stagger_s=0.01, short_life_s=0.1, attempt_life_s=0.4,
                            stagger_s=0.2)
    with attempts_on_virtual_time(monkeypatch, hanging), pytest.raises(DialTimeout):
        await dial("127.0.0.1", 9, timeout_s=0.6, settings=settings, outage_age_s=0.0)
    assert hanging.started > 20
    # ~10 short ones (0.1 s / 10 ms) and 2 long ones (0.4 s / 0.2 s); without expiry
    # all ~60 would have been open at the end.
    assert hanging.most_at_once <= 20, hanging.most_at_once
    assert hanging.cancelled == hanging.started


async def test_a_full_set_of_attempts_gives_up_short_ones_not_the_long_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A path with an RTT longer than ``max_in_flight`` staggers: only the first (long)
    attempt's SYN-ACK comes in time, and it must still be open when it does."""
    hanging = HangingConnects()
    calls = 0

    async def slow_first(sock: socket.socket, address: Any) -> None:
        nonlocal calls
        calls += 1
        if calls == 1:
            await asyncio.sleep(0.2)  # the long RTT: this attempt's SYN-ACK comes late
            return
        await hanging(sock, address)

    settings = DialSettings(max_in_flight=5, stagger_s=1.0)  # 5 x 10 ms << 0.2 s
    with attempts_on_virtual_time(monkeypatch, slow_first):
        sock = await dial("127.0.0.1", 9, timeout_s=1.0, settings=settings, outage_age_s=0.0)
    sock.close()
    assert hanging.started >= 10  # the short ones kept coming and were given up
    assert hanging.most_at_once <= 4  # 5 open at most, the long one among them


class LoserCleanupsPerPass:
    """Counts, for each pass of the event loop while it runs, how many attempts of
    *connects* were cancelled (closed) in that pass."""

    def __init__(self, connects: HangingConnects) -> None:
        self.connects = connects
        self.per_pass: list[int] = []
        self.task = asyncio.create_task(self._tick())

    async def _tick(self) -> None:
        seen = self.connects.cancelled
        while True:
            await asyncio.sleep(0)  # one pass of the loop
            self.per_pass.append(self.connects.cancelled - seen)
            seen = self.connects.cancelled

    async def stop(self) -> list[int]:
        self.task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self.task
        return self.per_pass


async def test_the_winner_comes_back_before_the_losers_are_closed_one_per_pass(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The 20th attempt connects while 19 are open: the dial returns it before closing
    those (all at once they held the winner back ~0.9 ms at the moment the link is
    back), and then closes every loser, never more than one per pass of the loop."""
    hanging = HangingConnects()
    calls = 0

    async def twentieth_connects(sock: socket.socket, address: Any) -> None:
        nonlocal calls
        calls += 1
        if calls != 20:
            await hanging(sock, address)

    monkeypatch.setattr(asyncio.get_running_loop(), "sock_connect", twentieth_connects)
    cleanups = LoserCleanupsPerPass(hanging)
    sock = await dial("127.0.0.1", 9, timeout_s=5.0, outage_age_s=0.0)
    sock.close()
    assert hanging.started == 19
    assert hanging.cancelled <= 1  # returned first
    await wait_until(lambda: hanging.cancelled == 19)
    per_pass = await cleanups.stop()
    assert max(per_pass) == 1, per_pass


async def test_dial_first_returns_the_winner_before_closing_the_other_targets_dials(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Two targets, both silent past the head start, then the second's attempt
    connects: it is returned while the first target's attempts are still open, and they
    are all closed soon after."""
    hanging = HangingConnects()
    connect_second = asyncio.get_running_loop().create_future()

    async def second_connects_when_told(sock: socket.socket, address: Any) -> None:
        if address[1] == 2 and not connect_second.done():
            await connect_second
            return
        await hanging(sock, address)

    with attempts_on_virtual_time(monkeypatch, second_connects_when_told) as loop:
        loop.call_later(0.15, connect_second.set_result, None)  # after the 0.05 s head start
        index, sock = await dial_first([("127.0.0.1", 1), ("127.0.0.1", 2)], 5.0,
                                       head_start_s=0.05, outage_age_s=0.0)
    sock.close()
    assert index == 1
    assert hanging.started >= 10
    assert hanging.cancelled < hanging.started  # returned first
    await wait_until(lambda: hanging.cancelled == hanging.started)


class TimedConnects(HangingConnects):
    """:class:`HangingConnects` that also notes when each attempt started (loop time)."""

    def __init__(self) -> None:
        super().__init__()
        self.times: list[float] = []

    async def __call__(self, sock: socket.socket, address: Any) -> None:
        self.times.append(asyncio.get_running_loop().time())
        await super().__call__(sock, address)


async def resolved_at_once(host: str, port: int, **_: Any) -> list[Any]:
    """``loop.getaddrinfo`` without its executor thread, whose answer virtual time would
    not wait for."""
    return [(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP, "", (host, port))]


async def test_an_attempt_starts_just_before_each_expected_message(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A 20 Hz and a 10 Hz topic, paced SYNs every 50 ms: without *ahead* most messages
    have no attempt in the ``ahead_s`` before them; with it, every one has.

    On virtual time: on a loaded host (load 5) the real loop woke more than 2 ms late
    and an attempt landed after its message; what is tested is the dialer's schedule."""
    loop = asyncio.get_running_loop()
    settings = DialSettings(fast_stagger_s=0.05, outage_stagger_s=0.05, ahead_s=0.005)

    async def run(use_ahead: bool) -> tuple[list[float], list[float]]:
        """The attempts' start times, and the messages expected in the dial's 0.6 s
        (the last ones left out: the dial may end before their attempt)."""
        start = loop.time()
        expected = sorted([start + 0.0137 + k * 0.05 for k in range(11)]
                          + [start + 0.0411 + k * 0.1 for k in range(5)])

        def ahead() -> float:
            now = loop.time()
            return min((t for t in expected if t > now + settings.ahead_s),
                       default=math.inf) - now

        timed = TimedConnects()
        monkeypatch.setattr(loop, "sock_connect", timed)
        monkeypatch.setattr(loop, "getaddrinfo", resolved_at_once)
        with pytest.raises(DialTimeout):
            await dial("127.0.0.1", 9, timeout_s=0.6, settings=settings, outage_age_s=0.0,
                       ahead=ahead if use_ahead else None)
        return timed.times, expected

    def covered(times: list[float], expected: list[float]) -> int:
        # An attempt in the ahead_s before the message.
        return sum(any(t - settings.ahead_s <= a <= t for a in times) for t in expected)

    with virtual_time(loop):
        paced, expected = await run(use_ahead=False)
        timed, expected = await run(use_ahead=True)
    assert covered(paced, expected) < len(expected) / 2
    assert covered(timed, expected) == len(expected), (timed, expected)
    # One extra attempt per expected message, no more.
    assert len(timed) <= len(paced) + len(expected) + 1


async def test_ahead_attempts_are_bounded_however_many_topics(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Messages expected every 0.1 ms (hundreds of topics): still one attempt per
    ``ahead_s`` at most; and none of it once the outage is past ``fast_for_s``."""
    hanging = HangingConnects()
    settings = DialSettings(ahead_s=0.01, fast_stagger_s=1.0, outage_stagger_s=1.0,
                            stagger_s=1.0)
    with attempts_on_virtual_time(monkeypatch, hanging), pytest.raises(DialTimeout):
        await dial("127.0.0.1", 9, timeout_s=0.3, settings=settings, outage_age_s=0.0,
                   ahead=lambda: 0.0001)
    assert 29 <= hanging.started <= 31, hanging.started  # 0.3 s / 10 ms
    late = HangingConnects()
    with attempts_on_virtual_time(monkeypatch, late), pytest.raises(DialTimeout):
        await dial("127.0.0.1", 9, timeout_s=0.3, settings=settings, outage_age_s=61.0,
                   ahead=lambda: 0.0001)
    assert late.started == 1  # the slow pace only: one attempt a second


@pytest.mark.netns
@NEEDS_ROOT
async def test_fast_pace_connects_within_tens_of_ms_of_the_restore(link: Link) -> None:
    """Cut, dial as at the start of an outage, restore after 0.3 s: the next 10 ms SYN
    connects (the slow pace took up to 0.25 s, the kernel's own resend 1 s)."""
    shaper = LinkShaper(host_run, link.dev, detect(host_run, link.dev))
    loop = asyncio.get_running_loop()
    address = (link.peer_ip, SINK_TCP_PORT)
    socket.create_connection(address, timeout=5.0).close()  # neighbour entry resolved
    shaper.cut()
    try:
        restored: list[float] = []

        def restore() -> None:
            shaper.restore()
            restored.append(loop.time())

        loop.call_later(0.3, restore)  # the cut's length is the scenario
        sock = await dial(*address, timeout_s=5.0, outage_age_s=0.0)
        sock.close()
        after_s = loop.time() - restored[0]
    finally:
        shaper.clear()
    assert after_s < 0.1, after_s
