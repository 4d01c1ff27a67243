"""The robot's standby connection: a second, idle WebSocket to the relay, taken over the
moment a cut link returns (issue 19; docs/recovery.md, "The standby connection").

Why: after a cut the robot's connection holds data the kernel retransmits with an
exponential backoff, so the link gives it up and opens a new one, whose WebSocket upgrade
costs a round trip plus the server's handshake work (4-13 ms over the e2e's WireGuard
link) before fresh data flows. A 10 Hz topic whose first message after the restore falls
in that window arrives late and loses a whole period. A connection that sent nothing
since the cut has nothing to retransmit: the first write on it after the restore leaves at
once. So the robot keeps one such connection open beside the one it uses, upgraded and
authenticated but sending nothing (``X-Fleetctl-Standby: 1`` on the upgrade: the server
attaches no session to it and sends it nothing). When a dial shows the path works again
(the link's SYN probes), the keeper sends ``{"type": "activate"}`` on the standby, which
makes the server move the robot's session onto it (the usual takeover), and the fresh
frames follow in the same flight. The socket that dial connected becomes the next
standby once the activated connection has its first pong.

Only to a server that offered it (the same header on its upgrade response): an older
fleetctl server or another Robofleet-convention server never sees one.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import random
import socket
from collections.abc import Awaitable, Callable
from typing import Any, Protocol

from websockets.exceptions import ConnectionClosed
from websockets.protocol import State

logger = logging.getLogger("fleetctl.client.link")

STANDBY_HEADER = "X-Fleetctl-Standby"  # fleetctl.server.sessions.STANDBY_HEADER
ACTIVATE = json.dumps({"type": "activate"})

# TCP keepalive on the standby's socket: seconds idle before the first probe, seconds
# between probes, unanswered probes before the kernel gives the connection up.
# Why: the standby carries nothing for hours, and a NAT (a robot's LTE carrier, a site
# router) may forget an idle TCP mapping long before RFC 5382's two hours; the standby would
# then fail the moment it is needed. A probe every 25 s (WireGuard's advice for its own
# keepalive) keeps the mapping, and carries no data: it never shows as unacknowledged, so
# an activation is not held behind it. Four unanswered probes (125 s) end a standby the
# network lost, and the keeper opens another; a cut shorter than about 100 s leaves it be.
KEEPALIVE_IDLE_S = 25
KEEPALIVE_INTERVAL_S = 25
KEEPALIVE_PROBES = 4


def keep_mapping_alive(sock: socket.socket) -> None:
    """Turn on the standby's TCP keepalive (:data:`KEEPALIVE_IDLE_S` and the rest)."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE, KEEPALIVE_IDLE_S)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL, KEEPALIVE_INTERVAL_S)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT, KEEPALIVE_PROBES)


class StandbyWebSocket(Protocol):
    """What this module needs of a client connection (websockets' ``ClientConnection``)."""

    @property
    def state(self) -> State: ...
    @property
    def transport(self) -> Any: ...
    def __aiter__(self) -> Any: ...
    async def send(self, message: str) -> None: ...
    async def close(self, code: int = 1000, reason: str = "") -> None: ...


# (socket connected to replica i, i) -> the connection upgraded as a standby.
Upgrade = Callable[[socket.socket, int], Awaitable[StandbyWebSocket]]
# () -> a socket connected to the current replica, and its index.
Dial = Callable[[], Awaitable[tuple[socket.socket, int]]]
# The socket's count of unacknowledged segments (TCP_INFO), None when unknown.
Unacked = Callable[[Any], "int | None"]


class Standby:
    """Keeps at most one standby connection; opens it only while the main one works.

    Args:
        upgrade: Upgrades a connected socket as a standby.
        dial: Connects a socket to the current replica (normal pace: the path works).
        unacked: Reads the kernel's unacknowledged segments of a socket.
        retry_min_s: First wait after a failed open, seconds (doubles per failure).
        retry_max_s: Cap of that wait, seconds.
        rng: Draws each wait's jitter (injected for tests).
    """

    def __init__(self, upgrade: Upgrade, dial: Dial, unacked: Unacked, *,
                 retry_min_s: float = 1.0, retry_max_s: float = 30.0,
                 rng: random.Random | None = None) -> None:
        self._upgrade = upgrade
        self._dial = dial
        self._unacked = unacked
        self._retry_min_s = retry_min_s
        self._retry_max_s = retry_max_s
        self._retry_s = retry_min_s
        self._rng = rng if rng is not None else random.Random()
        self._ws: StandbyWebSocket | None = None
        self._replica: int | None = None
        self._reader: asyncio.Task[None] | None = None
        self._opener: asyncio.Task[None] | None = None
        # A socket the last activation's dial connected: the next standby, upgraded once
        # the activated connection has its first pong (not before: its upgrade would
        # travel, and be handled by the server, ahead of the fresh frames).
        self._adopted: tuple[socket.socket, int] | None = None
        self._main_up = False
        self._closed = False
        self.counters = {"opened": 0, "open_failures": 0, "activations": 0, "lost": 0,
                         "unusable": 0}

    @property
    def connection(self) -> StandbyWebSocket | None:
        """The standby connection, if one is open."""
        return self._ws

    def main_up(self, supported: bool) -> None:
        """The main connection works (its first pong): open a standby if the server
        offers them (*supported*) and none is open or opening."""
        self._main_up = supported
        self._retry_s = self._retry_min_s  # a new main connection: a fresh start
        if supported:
            self._open_soon(0.0)
        elif self._adopted is not None:
            self._adopted[0].close()
            self._adopted = None

    def main_down(self) -> None:
        """The main connection ended: open nothing until one works again."""
        self._main_up = False

    def adopt(self, sock: socket.socket, replica: int) -> None:
        """*sock* (connected to *replica*) becomes the next standby at :meth:`main_up`."""
        if self._adopted is not None:
            self._adopted[0].close()
        self._adopted = (sock, replica)

    async def activate(self, replica: int) -> StandbyWebSocket | None:
        """Activate the standby and hand it over, if it reaches *replica*, is open and
        has nothing unacknowledged (a write on it would otherwise wait for the kernel's
        retransmission); None otherwise (an unusable standby is closed).

        ``{"type": "activate"}`` goes out first, before this keeper's reader is stopped
        and before the caller's own work on the new connection: the server's takeover
        then runs while the robot prepares its first frames. A standby that closed
        meanwhile is still handed over: the caller's next send on it says so."""
        ws = self._ws
        if ws is None:
            return None
        usable = (self._replica == replica and ws.state is State.OPEN
                  and self._unacked(ws.transport.get_extra_info("socket")) == 0)
        if usable:
            with contextlib.suppress(ConnectionClosed):
                await ws.send(ACTIVATE)
        await self._stop_reader()
        self._ws = self._replica = None
        if not usable:
            self.counters["unusable"] += 1
            ws.transport.abort()
            return None
        self.counters["activations"] += 1
        return ws

    async def close(self) -> None:
        """Close the standby and stop opening new ones (the link stops)."""
        self._closed = True
        if self._opener is not None:
            self._opener.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._opener
        await self._stop_reader()
        if self._adopted is not None:
            self._adopted[0].close()
            self._adopted = None
        ws, self._ws = self._ws, None
        if ws is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.close(), 1.0)
            ws.transport.abort()

    def stats(self) -> dict[str, Any]:
        """Counters, and whether a standby is open now."""
        return {"open": self._ws is not None, **self.counters}

    # -- internals ----------------------------------------------------------------------

    def _open_soon(self, delay_s: float) -> None:
        if self._closed or self._ws is not None or (
                self._opener is not None and not self._opener.done()):
            return
        self._opener = asyncio.create_task(self._open(delay_s))

    async def _open(self, delay_s: float) -> None:
        if delay_s > 0:
            await asyncio.sleep(delay_s)  # a retry pace, not a synchronization
        if not self._main_up or self._closed:
            return  # the next main_up() opens it
        adopted, self._adopted = self._adopted, None
        try:
            sock, replica = adopted if adopted is not None else await self._dial()
            ws = await self._upgrade(sock, replica)
        except asyncio.CancelledError:
            if adopted is not None:
                adopted[0].close()
            raise
        except Exception as exc:  # refused, timed out, handshake failed: retry later
            self.counters["open_failures"] += 1
            logger.info("standby connection not opened (%r); next try in %.1f s", exc,
                        self._retry_later())
            return
        if self._closed:
            ws.transport.abort()
            return
        self._ws, self._replica = ws, replica
        self.counters["opened"] += 1
        self._reader = asyncio.create_task(self._read(ws))

    async def _read(self, ws: StandbyWebSocket) -> None:
        """Read what the server sends a standby (its welcome, an error, a close) until it
        closes; then open another while the main connection works."""
        try:
            async for message in ws:
                if isinstance(message, str) and '"error"' in message:
                    logger.warning("server on the standby connection: %.200s", message)
        except ConnectionClosed:
            pass
        if self._ws is ws:  # closed by the server or the network, not taken
            self._ws = self._replica = None
            self.counters["lost"] += 1
            rcvd = getattr(ws, "close_rcvd", None)
            logger.info("standby connection closed (%s); opening another in %.1f s",
                        rcvd or "no close frame", self._retry_later())

    def _retry_later(self) -> float:
        """Open again after the current wait times U(0.5, 1) jitter, and double the wait
        (up to its cap); called from the opener or the reader, whose task is ending.

        The jitter is the reconnect backoff's (``transport.backoff_delay_s``) for the same
        reason: a relay restart closes every robot's standby at once, and a fleet that
        retried in step would hit the new relay's handshakes in one burst."""
        delay, self._retry_s = self._retry_s, min(self._retry_max_s, self._retry_s * 2)
        delay *= self._rng.uniform(0.5, 1.0)
        self._opener = None
        self._open_soon(delay)
        return delay

    async def _stop_reader(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None and not reader.done():
            reader.cancel()  # websockets' recv() may be cancelled safely
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await reader
