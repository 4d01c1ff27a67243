"""The relay server: websockets + HTTP on one port, wired to :class:`RelayCore`.

Use :class:`RelayServer` as an async context manager (tests, benchmarks) or
:func:`run_server` (``fleetctl server``), which also handles SIGTERM/SIGINT.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import http
import logging
import signal
import ssl
from collections.abc import Callable
from typing import Any

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from fleetctl.server import endpoints, protocol
from fleetctl.server.authmap import AuthMap, Identity, IPAddress, load_auth_map
from fleetctl.server.config import ServerConfig
from fleetctl.server.connection import RelayConnection
from fleetctl.server.identity import bearer_token, effective_address, parse_address
from fleetctl.server.metrics import Metrics
from fleetctl.server.outbound import OutboundScheduler
from fleetctl.server.registry import RobotRegistry
from fleetctl.server.relay import Peer, RelayCore
from fleetctl.server.sessions import SESSION_HEADER

log = logging.getLogger("fleetctl.server")
# websockets logs every request header (Authorization: Bearer ...) at DEBUG; its logger
# for our connections is pinned at INFO so tokens never reach a log, whatever the root level.
ws_log = logging.getLogger("fleetctl.server.websockets")
ws_log.setLevel(logging.INFO)

# Why small: the kernel socket buffer already holds plenty; bytes parked in asyncio's
# buffer cannot be dropped or superseded, bytes in our scheduler can (Pound, Robofleet n_T).
WRITE_LIMIT_BYTES = 16 * 1024
# Bytes the writer takes from the scheduler per transport write.
WRITE_BATCH_BYTES = 64 * 1024
REGISTRY_FLUSH_PERIOD_S = 1.0


class RelayServer:
    """A running relay.

    Args:
        config: Server config; ``listen_port`` 0 picks a free port (see :attr:`port`).
        auth: Auth map; read from ``config.auth_map`` when ``None``.
    """

    def __init__(self, config: ServerConfig, auth: AuthMap | None = None) -> None:
        self.config = config
        self.auth = auth if auth is not None else load_auth_map(config.auth_map)
        self.metrics = Metrics()
        self.registry = RobotRegistry(config.database, config.limits.robot_offline_after_s)
        self.core = RelayCore(config, self.auth, self.registry, self.metrics)
        self._server: Server | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._flusher: asyncio.Task[None] | None = None

    @property
    def port(self) -> int:
        """The bound TCP port."""
        assert self._server is not None, "server not started"
        port: int = next(iter(self._server.sockets)).getsockname()[1]
        return port

    @property
    def url(self) -> str:
        """``ws://host:port/`` (``wss`` with TLS) of the bound socket."""
        scheme = "wss" if self.config.tls_cert else "ws"
        host = next(iter(self._server.sockets)).getsockname()[0] if self._server else "?"
        return f"{scheme}://{host}:{self.port}/"

    async def start(self) -> None:
        """Bind and start serving."""
        self._server = await serve(
            self._handler,
            self.config.listen_host,
            self.config.listen_port,
            create_connection=RelayConnection,
            process_request=self._process_request,
            process_response=self._process_response,
            max_size=self.config.limits.max_frame_bytes,
            max_queue=16,
            write_limit=WRITE_LIMIT_BYTES,
            ssl=self._ssl_context(),
            logger=ws_log,
            compression=None,  # per-message deflate costs CPU per frame; payloads are binary
        )
        self._flusher = asyncio.create_task(self._flush_registry())
        log.info("relay listening on %s", self.url)

    async def stop(self) -> None:
        """Close every connection (1001), stop listening, flush the registry."""
        if self._flusher is not None:
            self._flusher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._flusher
        if self._server is not None:
            self._server.close(close_connections=True)
            await self._server.wait_closed()
        for task in list(self._tasks):
            task.cancel()
        self.registry.close()

    async def __aenter__(self) -> RelayServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    def _ssl_context(self) -> ssl.SSLContext | None:
        if self.config.tls_cert is None or self.config.tls_key is None:
            return None
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        context.load_cert_chain(self.config.tls_cert, self.config.tls_key)
        return context

    async def _flush_registry(self) -> None:
        while True:  # periodic write-behind and session expiry, not synchronization
            await asyncio.sleep(REGISTRY_FLUSH_PERIOD_S)
            try:
                self.registry.flush()
            except Exception:  # a full disk must not stop the relay
                log.exception("robot registry flush failed")
            self.core.sessions.expire()

    # -- handshake ----------------------------------------------------------------------

    def _address(self, connection: ServerConnection, request: Request) -> IPAddress | None:
        remote = connection.remote_address
        peer = parse_address(remote[0] if remote else None)
        return effective_address(
            peer, request.headers.get("X-Forwarded-For"), self.config.trusted_proxies
        )

    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        path = request.path.split("?", 1)[0]
        if path == "/healthz":
            return endpoints.text(http.HTTPStatus.OK, "ok\n")
        if path == "/metrics":
            body = self.metrics.render(self._gauges(), self.core.session_gauges()).encode()
            return endpoints.response(http.HTTPStatus.OK, body,
                                      endpoints.PROMETHEUS_CONTENT_TYPE)
        if path == "/robots" and "upgrade" not in request.headers.get("Connection", "").lower():
            return self._robots(connection, request)
        return None

    def _robots(self, connection: ServerConnection, request: Request) -> Response:
        address = self._address(connection, request)
        identities, bad = self._identities(address, request)
        perms = self.core.pool.get(identities) if identities else None
        allowed, perms = endpoints.robots_allowed(address, perms, bad)
        if not allowed:
            return endpoints.text(http.HTTPStatus.UNAUTHORIZED,
                                  "GET /robots needs loopback or a valid Bearer token\n")
        if perms is None:
            return endpoints.json_response({"robots": self.registry.as_json()})
        return endpoints.json_response({"robots": self.core.robots_for(perms)})

    def _identities(
        self, address: IPAddress | None, request: Request
    ) -> tuple[list[Identity], bool]:
        identities = self.auth.match_address(address)
        token = bearer_token(request.headers.get("Authorization"))
        if token is None:
            return identities, False
        found = self.auth.match_token(token)
        if found is None:
            return identities, True
        return [*identities, found], False

    def _process_response(
        self, connection: ServerConnection, request: Request, response: Response
    ) -> None:
        if response.status_code != http.HTTPStatus.SWITCHING_PROTOCOLS:
            return
        assert isinstance(connection, RelayConnection)
        address = self._address(connection, request)
        wake = asyncio.Event()
        names = request.headers.get_all(SESSION_HEADER)
        # Several headers: keep them all as one (invalid) name, refused on authentication.
        session_name = ",".join(names) if names else None
        peer = self.core.new_peer(
            str(address) if address else None, close=self._closer(connection), wake=wake.set,
            session_name=session_name,
        )
        identities, bad = self._identities(address, request)
        connection.relay_state = (peer, identities, bad, wake)
        core = self.core

        def sink(frame: bytes) -> bool:
            if peer.perms is None:
                return False  # not authenticated yet: keep order with the token frame
            if not peer.closing:
                core.on_binary(peer, frame)
            return True

        connection.frame_sink = sink
        connection.on_lost = lambda: core.close_peer(peer)

    def _closer(self, connection: RelayConnection) -> Callable[[int, str], None]:
        def close(code: int, reason: str) -> None:
            # Called from inside data_received or the relay: close in a task, keep a ref.
            task = asyncio.get_running_loop().create_task(self._close(connection, code, reason))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

        return close

    async def _close(self, connection: RelayConnection, code: int, reason: str) -> None:
        state = connection.relay_state
        if state is not None:
            # Let queued control frames (the error that explains the close) go first.
            peer: Peer = state[0]
            with contextlib.suppress(ConnectionClosed):
                await connection.send_frames(
                    [f for _, f in peer.outbound.pop_batch(WRITE_BATCH_BYTES)
                     if isinstance(f, str)]
                )
        await connection.close(code, reason)

    # -- connection ---------------------------------------------------------------------

    async def _handler(self, connection: ServerConnection) -> None:
        assert isinstance(connection, RelayConnection)
        peer, identities, bad_token, wake = connection.relay_state
        writer = asyncio.create_task(self._write_loop(connection, peer, wake))
        try:
            if bad_token:
                self.core.on_token(peer, "")
            elif identities:
                self.core.authenticate(peer, identities)
            else:
                asyncio.get_running_loop().call_later(
                    self.config.limits.auth_timeout_s, self._auth_timeout, peer
                )
            await self._read_loop(connection, peer)
        finally:
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await writer
            self.core.close_peer(peer)
            if connection.close_code == protocol.CLOSE_TOO_BIG:
                self.metrics.count_close(protocol.CLOSE_TOO_BIG)

    def _auth_timeout(self, peer: Peer) -> None:
        if peer.perms is None and not peer.closing:
            peer.close(protocol.CLOSE_NO_IDENTITY, "no identity: no token frame in time")

    async def _read_loop(self, connection: RelayConnection, peer: Peer) -> None:
        # Only text frames and fragmented binary messages arrive here; complete binary
        # frames went through the sink already.
        with contextlib.suppress(ConnectionClosed):
            async for message in connection:
                if peer.closing:
                    pass
                elif isinstance(message, str):
                    self.core.on_text(peer, message)
                else:
                    self.core.on_binary(peer, message)
                connection.message_handled()

    async def _write_loop(
        self, connection: RelayConnection, peer: Peer, wake: asyncio.Event
    ) -> None:
        outbound, metrics = peer.outbound, self.metrics
        with contextlib.suppress(ConnectionClosed):
            while True:
                if not len(outbound):
                    wake.clear()
                    await wake.wait()
                batch = outbound.pop_batch(WRITE_BATCH_BYTES)
                for topic, frame in batch:
                    metrics.count_out(topic, len(frame))
                await connection.send_frames([frame for _, frame in batch])
                mark = outbound.ack_mark()  # None unless the peer has a session
                if mark is not None:
                    await self._ack_point(connection, outbound, mark)

    @staticmethod
    async def _ack_point(connection: RelayConnection, outbound: OutboundScheduler,
                         mark: int) -> None:
        """Ping after session no_drop frames: the pong (the client answers pings in order,
        after reading what came before) acknowledges them (see OutboundScheduler)."""
        waiter = asyncio.ensure_future(await connection.ping(mark.to_bytes(8, "big")))
        waiter.add_done_callback(functools.partial(_on_pong, outbound, mark))

    def _gauges(self) -> list[tuple[str, str, dict[str, float]]]:
        depth = {p.label: float(len(p.outbound)) for p in self.core.peers.values()}
        nbytes = {p.label: float(p.outbound.queued_bytes) for p in self.core.peers.values()}
        dropped = {p.label: float(p.outbound.dropped_total) for p in self.core.peers.values()}
        return [
            ("fleetctl_outbound_queue_frames", "Frames queued per connection.", depth),
            ("fleetctl_outbound_queue_bytes", "Bytes queued per connection.", nbytes),
            ("fleetctl_outbound_dropped", "Frames dropped per open connection.", dropped),
        ]


def _on_pong(outbound: OutboundScheduler, mark: int, waiter: asyncio.Future[float]) -> None:
    # A closed connection fails its waiters: then take_no_drop() keeps the frames.
    if not waiter.cancelled() and waiter.exception() is None:
        outbound.acked(mark)


async def run_server(config: ServerConfig, ready: Callable[[RelayServer], None] | None = None,
                     stop: asyncio.Event | None = None) -> None:
    """Run until SIGTERM/SIGINT (or *stop* is set), then shut down gracefully.

    Args:
        config: The server config.
        ready: Called with the started server (e.g. to print the URL).
        stop: Optional event that stops the server when set.
    """
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    async with RelayServer(config) as server:
        if ready is not None:
            ready(server)
        await stop.wait()
        log.info("shutting down")
