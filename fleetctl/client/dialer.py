"""Open a TCP connection fast on a link that is coming back: staggered, racing SYNs.

Why: Linux retransmits a lost SYN only after 1 s, then 3 s, 7 s. A connection attempt
started just before a dropout ends therefore sits idle for up to a second after the link is
back (measured in the e2e ``dropout`` scenario: ~0.9 s of nothing after the restore). A
fresh attempt is started every ``stagger_s`` while the earlier ones are still waiting, so a
SYN leaves at most ``stagger_s`` after the link returns. The first attempt to connect wins;
the others are closed before anything is sent on them, so the server sees at most a bare
TCP connection close, never a second WebSocket handshake (which would take over the
robot's session).

Cost: one ~60-byte SYN per ``stagger_s`` while the server is unreachable, and at most
``max_in_flight`` half-open sockets; an attempt older than that many staggers is dropped.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from dataclasses import dataclass

__all__ = ["DialSettings", "dial"]


@dataclass(frozen=True)
class DialSettings:
    """How :func:`dial` races its attempts.

    Args:
        stagger_s: A new attempt starts this long after the previous one, seconds.
        max_in_flight: Attempts waiting at once; the oldest is abandoned for a new one.
    """

    stagger_s: float = 0.25
    max_in_flight: int = 8


async def dial(host: str, port: int, timeout_s: float, settings: DialSettings = DialSettings(),
               local_addr: tuple[str, int] | None = None) -> socket.socket:
    """Return a connected non-blocking TCP socket to *host*:*port*.

    The addresses *host* resolves to are tried in order, as the event loop's own
    ``create_connection`` does: ``localhost`` may resolve to ``::1`` first while the
    server listens on 127.0.0.1 only.

    Raises:
        TimeoutError: No attempt connected within *timeout_s*.
        OSError: The name did not resolve, or every address refused or was unreachable
            (the server is reachable and said no: retrying at once would not help).
    """
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(timeout_s):
        infos = await loop.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        error: OSError | None = None
        for family, _, proto, _, address in infos:
            try:
                return await _race(family, proto, address, local_addr, settings)
            except OSError as exc:
                error = exc
        raise error or OSError(f"{host} resolved to no address")


async def _race(family: int, proto: int, address: tuple[str, int] | tuple[str, int, int, int],
                local_addr: tuple[str, int] | None, settings: DialSettings) -> socket.socket:
    """Staggered attempts to one address until one connects or one is refused."""
    attempts: list[asyncio.Task[socket.socket]] = []
    try:
        while True:
            if len(attempts) >= settings.max_in_flight:
                oldest = attempts.pop(0)
                oldest.cancel()
            attempts.append(asyncio.create_task(_attempt(family, proto, address, local_addr)))
            done, _ = await asyncio.wait(attempts, timeout=settings.stagger_s,
                                         return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                attempts.remove(task)
                return task.result()  # a refusal or unreachable network raises here
    finally:
        for task in attempts:
            task.cancel()
        for task in attempts:
            with contextlib.suppress(asyncio.CancelledError, OSError):
                (await task).close()  # one that connected while being cancelled


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
