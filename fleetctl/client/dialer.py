"""Open a TCP connection fast on a link that is coming back: staggered, racing SYNs.

Why: Linux retransmits a lost SYN only after 1 s, then 3 s, 7 s. A connection attempt
started just before a dropout ends therefore sits idle for up to a second after the link is
back (measured in the e2e ``dropout`` scenario: ~0.9 s of nothing after the restore). A
fresh attempt is started every stagger while the earlier ones are still waiting, so a
SYN leaves at most one stagger after the link returns. The first attempt to connect wins;
the others are closed before anything is sent on them, so the server sees at most a bare
TCP connection close, never a second WebSocket handshake (which would take over the
robot's session).

Faster in an outage (issue 19): a link cut for a few seconds, or for half a minute,
should be back within milliseconds, so the stagger starts at ``fast_stagger_s`` when the
outage begins, doubles every ``double_every_s`` up to ``outage_stagger_s``, stays there
until the outage is ``fast_for_s`` old, and only then falls to the slow pace ``stagger_s``
(:meth:`DialSettings.stagger_at`). The defaults make it flat: 10 ms for a minute; an
operator who sets a slower outage pace (client.yaml ``outage_dial_interval_s``) gets the
doubling from 10 ms up to it. The outage's age comes from the caller (``outage_age_s``):
a dial that timed out and is started again continues the pace instead of starting over.
Why a minute: the e2e ``peer`` scenario's 30 s cuts at the slow pace took 0.245-0.327 s
to recover (a SYN up to 0.25 s after the restore), against the 0.1 s bar; a robot out of
coverage for longer than a minute has a coverage problem that a few tens of milliseconds
do not change, and then the bound below drops to its floor. Why 10 ms: a topic whose
first message after the restore is published before the next SYN leaves loses a period
(docs/recovery.md, the trade-off), with probability ~stagger / (2 x period) per cut: 5 %
for a 10 Hz scan at 10 ms, 10-20 % at the 20-40 ms of before.

Dialing ahead of the next message (issue 19). A message published before the winning
SYN's answer came back is dropped as stale (``Scheduler.drop_stale``: it may have been
published while the path was dead), so a link that returned in the 10 ms between two
paced SYNs cost the message published in that gap a whole period (traced e2e ``peer``
runs: the cause in 4 of 12 trials). The caller can pass *ahead*, the time to the next
message it wants an attempt ahead of, and an extra attempt then starts ``ahead_s``
(1.5 ms) before it, no sooner than ``ahead_s`` after the previous one. The RobotLink
asks for two per expected publish, 3 and 1.5 ms ahead of it (more on a path with a long
SYN round trip): the path has been seen to work when the message is published unless
the link came back in the last 1.5 ms before it. (Until 2026-12-05 one attempt, 3 ms
ahead of the next *offer*, which comes 0.5-3 ms after the publish: a traced run had the
SYN for a scan leave 0.4 ms before its publish and its answer come after it, so the scan
went as possibly stale; docs/recovery.md, "Aimed at the publish".) The intake of the e2e
load's topics keeps its period within 2 ms (0.6 ms at p99). At most one such attempt per
``ahead_s`` (666 a second, however many topics), only in the outage's first
``fast_for_s``; the e2e load (20 + 10 + 1 Hz) adds 62 a second.

Cost while the server is unreachable. Linux resends an unanswered SYN at 1 s. One attempt
per ``stagger_s`` is a long one: it lives ``attempt_life_s`` (2 s, so a path with an RTT
up to ~2 s still connects) and sends two SYNs; the extra attempts of the faster pace live
``short_life_s`` (0.9 s) and send one. Every SYN is ~60 bytes (74 on Ethernet, ~130 inside
WireGuard). So at most ``1/stagger_at(age) + 1/stagger_s`` SYNs a second, plus the
attempts ahead of messages (31/s, ~4 KB/s inside WireGuard for the e2e load): with the defaults
104/s (~7.7 KB/s, ~13.5 KB/s or 0.11 Mbit/s inside WireGuard) for the outage's first
minute, ~810 KB inside WireGuard in all, ~30 % of what the e2e ``peer`` load sends in
that minute when the link is up; 8/s (~600 B/s) after that. At most ``max_in_flight``
sockets are half open at once: the oldest short attempt is dropped for a new one (never a
long one while a short one is open); a dropped attempt in SYN-SENT sends nothing when
closed.

The losers of a won race are closed after the winner is returned: from ``REAP_AFTER_S``
on, one per pass of the event loop (:func:`_reap_soon`). Closing them first, all at once,
held the winner back by ~0.9 ms with the 64 attempts a cut of more than ~0.6 s leaves
open (more on a busy host), at the moment the link is back, when the first message after
the restore is being offered and sent; closed at once after the return, they delayed the
standby's activation instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

__all__ = ["Ahead", "DialSettings", "DialTimeout", "dial", "dial_first"]

Ahead = Callable[[], float]
"""Seconds from now to the next message the caller expects to send (``inf``: none)."""


class DialTimeout(TimeoutError):
    """No attempt connected in time and none was refused: the server is unreachable
    (silent). The dialer paced itself, so retrying at once costs no more than waiting."""


@dataclass(frozen=True)
class DialSettings:
    """How :func:`dial` races its attempts.

    Args:
        stagger_s: A new attempt starts this long after the previous one, seconds.
        max_in_flight: Attempts waiting at once; the oldest short one is abandoned for a
            new one.
        attempt_life_s: A long attempt (one per ``stagger_s``) is abandoned this old,
            seconds: the longest RTT a connect can have.
        short_life_s: The extra attempts of the fast pace are abandoned this old, seconds
            (before Linux resends their SYN at 1 s).
        fast_stagger_s: The stagger when an outage begins, seconds.
        double_every_s: The stagger doubles every this many seconds of outage, up to
            ``outage_stagger_s``.
        outage_stagger_s: The slowest stagger while the outage is younger than
            ``fast_for_s``, seconds.
        fast_for_s: From this age of an outage on, seconds, the slow pace ``stagger_s``.
        ahead_s: An attempt the caller asks for ahead of a message it expects (the
            *ahead* argument of :func:`dial`) starts this long before it, seconds, and
            no sooner than this after the previous attempt (at most ``1 / ahead_s`` of
            them a second, however many topics).
    """

    stagger_s: float = 0.25
    max_in_flight: int = 64
    attempt_life_s: float = 2.0
    short_life_s: float = 0.9
    fast_stagger_s: float = 0.01
    double_every_s: float = 8.0
    outage_stagger_s: float = 0.01
    fast_for_s: float = 60.0
    ahead_s: float = 0.0015

    def stagger_at(self, outage_age_s: float) -> float:
        """The stagger for an attempt started *outage_age_s* into an outage (``inf``: not
        in an outage, the slow pace)."""
        if outage_age_s >= self.fast_for_s:
            return self.stagger_s
        growth = math.pow(2.0, max(0.0, outage_age_s) / self.double_every_s)
        return min(self.outage_stagger_s, self.stagger_s, self.fast_stagger_s * growth)


async def dial(host: str, port: int, timeout_s: float, settings: DialSettings = DialSettings(),
               local_addr: tuple[str, int] | None = None,
               outage_age_s: float = math.inf, ahead: Ahead | None = None) -> socket.socket:
    """Return a connected non-blocking TCP socket to *host*:*port*.

    The addresses *host* resolves to are tried in order, as the event loop's own
    ``create_connection`` does: ``localhost`` may resolve to ``::1`` first while the
    server listens on 127.0.0.1 only.

    *outage_age_s* is how long the link has been down when the dial starts (``inf``, the
    default, when not in an outage: a first connection or after a refusal), which picks
    the stagger (:meth:`DialSettings.stagger_at`). *ahead*, asked right after each attempt
    starts, gives the seconds until the caller's next expected message (``inf``: none):
    while the outage is younger than ``fast_for_s``, an extra attempt starts
    ``settings.ahead_s`` before it (see the module docstring).

    Raises:
        DialTimeout: No attempt connected within *timeout_s* (a ``TimeoutError``).
        OSError: The name did not resolve, or every address refused or was unreachable
            (the server is reachable and said no: retrying at once would not help).
    """
    loop = asyncio.get_running_loop()
    started = loop.time() - outage_age_s

    def pause() -> float:
        age = loop.time() - started
        wait_s = settings.stagger_at(age)
        if ahead is not None and age < settings.fast_for_s:
            wait_s = min(wait_s, max(settings.ahead_s, ahead() - settings.ahead_s))
        return wait_s

    try:
        async with asyncio.timeout(timeout_s):
            infos = await loop.getaddrinfo(host, port, type=socket.SOCK_STREAM)
            error: OSError | None = None
            for family, _, proto, _, address in infos:
                try:
                    return await _race(family, proto, address, local_addr, settings, pause)
                except OSError as exc:
                    error = exc
            raise error or OSError(f"{host} resolved to no address")
    except TimeoutError as exc:
        raise DialTimeout(f"no answer from {host}:{port} within {timeout_s:.1f} s") from exc


async def dial_first(targets: Sequence[tuple[str, int]], timeout_s: float,
                     settings: DialSettings = DialSettings(), *, head_start_s: float,
                     local_addr: tuple[str, int] | None = None,
                     outage_age_s: float = math.inf,
                     ahead: Ahead | None = None) -> tuple[int, socket.socket]:
    """Dial ``targets[0]`` first; the others join after *head_start_s* (or at once when
    every running dial failed); the first to connect wins. Returns ``(index, socket)``.

    Why a head start rather than a plain race (issue 15, replicas): the caller lists its
    current replica first. On a link blip every replica is silent alike, and a plain race
    would hand the robot to whichever SYN-ACK happened to return first, moving its session
    for nothing; a replica that died is silent too, and after the head start the others
    take over. A replica that refuses (its process stopped, the port closed) is left at
    once. Each target is one :func:`dial` (its own staggered attempts, its own
    *timeout_s*, the same *ahead*); the losers are cancelled and a socket that connected
    late is closed.

    Raises:
        DialTimeout: No target connected and at least one was silent.
        OSError: Every target refused or was unreachable (the first target's error).
    """
    if len(targets) == 1:
        host, port = targets[0]
        return 0, await dial(host, port, timeout_s, settings, local_addr, outage_age_s, ahead)
    running: dict[asyncio.Task[socket.socket], int] = {}
    waiting = list(range(len(targets)))
    errors: dict[int, BaseException] = {}

    def start(indexes: list[int]) -> None:
        for i in indexes:
            host, port = targets[i]
            running[asyncio.create_task(
                dial(host, port, timeout_s, settings, local_addr, outage_age_s, ahead))] = i
        del waiting[:len(indexes)]

    start(waiting[:1])
    try:
        while running:
            done, _ = await asyncio.wait(running, timeout=head_start_s if waiting else None,
                                         return_when=asyncio.FIRST_COMPLETED)
            if not done:  # the head start is over
                start(list(waiting))
                continue
            for task in done:
                index = running.pop(task)
                exc = task.exception()
                if exc is None:
                    _reap_soon(running)
                    running.clear()
                    return index, task.result()
                if not isinstance(exc, OSError):  # TimeoutError is an OSError too
                    raise exc
                errors[index] = exc
            if not running and waiting:  # the first ones failed before the head start ended
                start(list(waiting))
    finally:
        await _cancel_and_close(running)
    timeouts = [e for e in errors.values() if isinstance(e, DialTimeout)]
    raise timeouts[0] if timeouts else errors[min(errors)]


@dataclass(eq=False)  # identity: removed from its list as itself
class _Attempt:
    """One open connect of a race: its task, when it is given up, and whether it is a
    long one (one per ``stagger_s``, living ``attempt_life_s``)."""

    task: asyncio.Task[socket.socket]
    expires: float
    long: bool


async def _race(family: int, proto: int, address: tuple[str, int] | tuple[str, int, int, int],
                local_addr: tuple[str, int] | None, settings: DialSettings,
                pause: Callable[[], float]) -> socket.socket:
    """Staggered attempts to one address until one connects or one is refused; *pause*,
    asked right after each attempt starts, gives the seconds to the next.

    The attempts report their end through one event rather than an ``asyncio.wait`` on
    all of them per stagger, which registers and removes a callback on each open attempt
    every round: at a 10 ms pace with 64 open that was most of the dialer's CPU while the
    link is down.
    """
    loop = asyncio.get_running_loop()
    attempts: list[_Attempt] = []  # in start order
    long_started = -math.inf  # the last long attempt (one per stagger_s)
    ended: list[asyncio.Task[socket.socket]] = []
    wake = asyncio.Event()

    def on_end(task: asyncio.Task[socket.socket]) -> None:
        if not task.cancelled():  # an abandoned attempt is no news
            ended.append(task)
            wake.set()

    try:
        while True:
            now = loop.time()
            while attempts:
                if len(attempts) >= settings.max_in_flight:
                    given_up = _oldest_short(attempts)
                else:
                    given_up = min(attempts, key=lambda a: a.expires)
                    if now < given_up.expires:
                        break
                attempts.remove(given_up)
                given_up.task.cancel()
            long = now - long_started >= settings.stagger_s * 0.999
            long_started = now if long else long_started
            task = asyncio.create_task(_attempt(family, proto, address, local_addr))
            task.add_done_callback(on_end)
            life = settings.attempt_life_s if long else settings.short_life_s
            attempts.append(_Attempt(task, now + life, long))
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(pause()):
                    await wake.wait()
            wake.clear()
            while ended:
                task = ended.pop(0)
                mine = next((a for a in attempts if a.task is task), None)
                if mine is None:  # abandoned as it connected: not the winner
                    with contextlib.suppress(OSError):
                        task.result().close()
                    continue
                attempts.remove(mine)
                won = task.result()  # a refusal or unreachable network raises here
                _reap_soon(a.task for a in attempts)
                attempts.clear()
                return won
    finally:
        await _cancel_and_close(a.task for a in attempts)


def _oldest_short(attempts: list[_Attempt]) -> _Attempt:
    """The attempt to abandon when ``max_in_flight`` are open: the oldest short one.

    Why not simply the oldest: at a 10 ms pace 64 attempts span 0.64 s, so the long
    attempts (the ones that wait ``attempt_life_s`` for a path with a long RTT, a
    satellite hop's ~0.6 s and more) would be abandoned before their SYN-ACK could come.
    """
    return next((a for a in attempts if not a.long), attempts[0])


# When the losers of a won race start being closed, seconds after the win: past the
# standby's activation and the messages offered right after it (the activation comes
# within ~2 ms of the win; a message offered ahead of it, within ``ahead_s``).
REAP_AFTER_S = 0.02
_reapers: set[asyncio.Task[None]] = set()  # strong references until each is done


def _reap_soon(tasks: Iterable[asyncio.Task[socket.socket]]) -> None:
    """Cancel and close the losers of a won race in the background: ``REAP_AFTER_S``
    after the win, then one per pass of the event loop, so that the winner is used at
    once and no pass spends more than one loser's cleanup (~15 us) ahead of the link's
    own work. A loser that connects in the meantime is closed too (the server sees a
    bare TCP close, as for any loser; a SYN-SENT socket sends nothing when closed)."""
    tasks = list(tasks)
    if tasks:
        reaper = asyncio.create_task(_reap_one_by_one(tasks))
        _reapers.add(reaper)
        reaper.add_done_callback(_reapers.discard)


async def _reap_one_by_one(tasks: list[asyncio.Task[socket.socket]]) -> None:
    left = list(reversed(tasks))
    try:
        await asyncio.sleep(REAP_AFTER_S)  # a pace, not a synchronization
        while left:
            await asyncio.sleep(0)  # yield a pass: the link's work comes first
            await _cancel_and_close([left.pop()])
    finally:  # cancelled itself (the loop is closing): the rest without waiting
        for task in left:
            if not task.done():
                task.cancel()  # the attempt closes its socket as it ends
            elif not task.cancelled() and task.exception() is None:
                task.result().close()


async def _cancel_and_close(tasks: Iterable[asyncio.Task[socket.socket]]) -> None:
    """Cancel the losers of a race; close a socket that connected while being cancelled."""
    tasks = list(tasks)
    for task in tasks:
        task.cancel()
    for task in tasks:
        with contextlib.suppress(asyncio.CancelledError, OSError):
            (await task).close()


async def _attempt(family: int, proto: int, address: tuple[str, int] | tuple[str, int, int, int],
                   local_addr: tuple[str, int] | None) -> socket.socket:
    sock = socket.socket(family, socket.SOCK_STREAM, proto)
    try:
        sock.setblocking(False)
        if local_addr is not None:
            sock.bind(local_addr)
        await asyncio.get_running_loop().sock_connect(sock, address)
    except BaseException:
        sock.close()  # a cancelled attempt closes its socket: the SYN-ACK meets a reset
        raise
    return sock
