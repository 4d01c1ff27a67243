"""The racing TCP dialer: loopback for the basics, a real cut link for the lost SYN."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time
from collections.abc import Iterator
from typing import Any

import pytest

from fleetctl.client.dialer import DialSettings, DialTimeout, dial, dial_first
from fleetctl.deploy.shaping import LinkShaper, detect
from tests.netns import NEEDS_ROOT, SINK_TCP_PORT, Link, host_run


async def test_connects_on_loopback() -> None:
    server = await asyncio.start_server(lambda r, w: w.close(), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        sock = await dial("127.0.0.1", port, timeout_s=5.0)
        try:
            assert sock.getpeername() == ("127.0.0.1", port)
            assert not sock.getblocking()
        finally:
            sock.close()


async def test_refused_is_raised_at_once() -> None:
    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    started = time.monotonic()
    with pytest.raises(ConnectionRefusedError):
        await dial("127.0.0.1", port, timeout_s=5.0)
    assert time.monotonic() - started < 1.0  # not retried until the deadline


async def test_next_address_is_tried_when_the_first_refuses(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Like ``localhost`` resolving to ::1 first while the server listens on 127.0.0.1."""
    server = await asyncio.start_server(lambda r, w: w.close(), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    loop = asyncio.get_running_loop()
    resolved = [
        (socket.AF_INET6, socket.SOCK_STREAM, 6, "", ("::1", port, 0, 0)),
        (socket.AF_INET, socket.SOCK_STREAM, 6, "", ("127.0.0.1", port)),
    ]

    async def getaddrinfo(*_: object, **__: object) -> list[Any]:
        return resolved

    monkeypatch.setattr(loop, "getaddrinfo", getaddrinfo)
    async with server:
        sock = await dial("dual-stack.test", port, timeout_s=5.0)
        try:
            assert sock.family == socket.AF_INET and sock.getpeername()[1] == port
        finally:
            sock.close()


async def test_unresolvable_name_is_an_os_error(monkeypatch: pytest.MonkeyPatch) -> None:
    # The resolver is patched: the tests send no DNS query off this machine.
    async def getaddrinfo(*_: object, **__: object) -> list[Any]:
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(asyncio.get_running_loop(), "getaddrinfo", getaddrinfo)
    with pytest.raises(OSError, match="not known"):
        await dial("no-such-host.test", 80, timeout_s=5.0)


@contextlib.contextmanager
def silent_port() -> Iterator[int]:
    """A loopback port that drops SYNs: a listener with a backlog of 0 whose queue is
    full (Linux drops a SYN it cannot queue), like a replica whose host died."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(0)
        port = listener.getsockname()[1]
        fillers = []
        try:
            for _ in range(3):
                filler = socket.socket()
                filler.setblocking(False)
                with contextlib.suppress(BlockingIOError):
                    filler.connect(("127.0.0.1", port))
                fillers.append(filler)
            yield port
        finally:
            for filler in fillers:
                filler.close()


def refused_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class Counting:
    """A loopback server that counts the connections it accepts."""

    def __init__(self) -> None:
        self.accepted = 0

    def handle(self, _: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.accepted += 1
        writer.close()


async def test_the_first_target_that_answers_is_kept_and_the_others_never_dialed() -> None:
    first, second = Counting(), Counting()
    a = await asyncio.start_server(first.handle, "127.0.0.1", 0)
    b = await asyncio.start_server(second.handle, "127.0.0.1", 0)
    async with a, b:
        targets = [("127.0.0.1", s.sockets[0].getsockname()[1]) for s in (a, b)]
        won, sock = await dial_first(targets, 5.0, head_start_s=0.5)
        sock.close()
        await wait_for(lambda: first.accepted == 1)
    assert won == 0 and second.accepted == 0


async def wait_for(predicate: Any, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not met in time"
        await asyncio.sleep(0.01)


async def test_a_silent_first_target_gives_way_after_the_head_start() -> None:
    server = await asyncio.start_server(lambda r, w: w.close(), "127.0.0.1", 0)
    async with server:
        port = server.sockets[0].getsockname()[1]
        with silent_port() as silent:
            started = time.monotonic()
            won, sock = await dial_first([("127.0.0.1", silent), ("127.0.0.1", port)], 5.0,
                                         head_start_s=0.3)
            elapsed = time.monotonic() - started
            sock.close()
    assert won == 1
    assert elapsed >= 0.3  # not before the head start: a blip must not move the robot


async def test_a_refusing_first_target_gives_way_at_once() -> None:
    server = await asyncio.start_server(lambda r, w: w.close(), "127.0.0.1", 0)
    async with server:
        port = server.sockets[0].getsockname()[1]
        won, sock = await dial_first([("127.0.0.1", refused_port()), ("127.0.0.1", port)],
                                     5.0, head_start_s=30.0)  # never reached
        sock.close()
    assert won == 1


async def test_every_target_refusing_raises_the_first_refusal() -> None:
    with pytest.raises(ConnectionRefusedError):
        await dial_first([("127.0.0.1", refused_port()), ("127.0.0.1", refused_port())],
                         5.0, head_start_s=0.1)


async def test_silence_somewhere_and_refusals_elsewhere_is_a_dial_timeout() -> None:
    """The caller redials at once after a DialTimeout (the dialer paced itself)."""
    with silent_port() as silent, pytest.raises(DialTimeout):
        await dial_first([("127.0.0.1", refused_port()), ("127.0.0.1", silent)], 0.5,
                         head_start_s=0.1)


@pytest.mark.netns
@NEEDS_ROOT
async def test_a_lost_syn_does_not_wait_for_tcp_retransmission(link: Link) -> None:
    """Cut the link, start a plain connect and the dialer, restore after 0.3 s: the
    plain connect's SYN was lost and Linux resends it only at 1 s; the dialer's next
    staggered SYN (every 0.25 s) gets through right after the restore."""
    shaper = LinkShaper(host_run, link.dev, detect(host_run, link.dev))
    loop = asyncio.get_running_loop()
    address = (link.peer_ip, SINK_TCP_PORT)
    # One connection first: the neighbour (ARP) entry is resolved before the cut, as it
    # is on a link that was working (an unresolved one is retried only every 1 s).
    socket.create_connection(address, timeout=5.0).close()
    shaper.cut()
    try:
        started = loop.time()

        async def plain() -> float:
            _, writer = await asyncio.open_connection(*address)
            writer.close()
            return loop.time() - started

        async def raced() -> float:
            sock = await dial(*address, timeout_s=5.0, settings=DialSettings(stagger_s=0.25))
            sock.close()
            return loop.time() - started

        # The cut's length is the scenario, not a synchronization.
        loop.call_later(0.3, shaper.restore)
        plain_s, raced_s = await asyncio.gather(plain(), raced())
    finally:
        shaper.clear()
    assert plain_s >= 0.9, plain_s  # the kernel's 1 s SYN retransmission
    assert 0.3 <= raced_s < 0.9, raced_s  # the next staggered SYN, not the 1 s resend
