"""The relay server: websockets + HTTP on one port, wired to :class:`RelayCore`.

With a ``web:`` section, a second listener (TLS) serves the same relay and the web page on
one HTTPS origin (:mod:`fleetctl.server.web`). The auth map is reloaded when its file
changes and on SIGHUP (:mod:`fleetctl.server.authreload`).

Use :class:`RelayServer` as an async context manager (tests, benchmarks) or
:func:`run_server` (``fleetctl server``), which also handles SIGTERM/SIGINT and SIGHUP.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import errno
import functools
import http
import logging
import signal
import socket
import ssl
from collections.abc import Awaitable, Callable
from typing import Any, NamedTuple, cast

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from fleetctl.errors import ConfigError
from fleetctl.linkdeflate import RelayDeflateFactory
from fleetctl.server import endpoints, firstframes, protocol
from fleetctl.server.admission import UnauthenticatedGate
from fleetctl.server.authmap import AuthMap, Identity, load_auth_map
from fleetctl.server.authreload import AuthReloader
from fleetctl.server.config import Hosts, ServerConfig, host_list, hosts_text
from fleetctl.server.connection import ABORT_AFTER_S, RelayConnection
from fleetctl.server.foxglove.adapter import TICKET_PATH, FoxgloveAdapter, TicketScrub
from fleetctl.server.handshake import (
    BadRequest,
    HandshakeLog,
    Upgrade,
    read_request,
    wants_websocket,
)
from fleetctl.server.heldpongs import HeldPongs
from fleetctl.server.identity import PROXY_HEADERS, parse_address, within
from fleetctl.server.metrics import Metrics
from fleetctl.server.msgtypes import codec_for
from fleetctl.server.outbound import OutboundScheduler
from fleetctl.server.recording.http import RECORDINGS_PATH, RecordingsEndpoint
from fleetctl.server.recording.recorder import Recorder
from fleetctl.server.registry import RobotRegistry
from fleetctl.server.relay import Peer, RelayCore
from fleetctl.server.sessions import STANDBY_HEADER
from fleetctl.server.tls import server_context
from fleetctl.server.web import QuietSuccess, page_response, web_page
from fleetctl.server.writethrough import ConnectionWriter, WriteThrough
from fleetctl.webviz.httpserver import WebPage

log = logging.getLogger("fleetctl.server")
# websockets logs every request header (Authorization: Bearer ...) at DEBUG; its logger
# for our connections is pinned at INFO so tokens never reach a log, whatever the root level.
ws_log = logging.getLogger("fleetctl.server.websockets")
ws_log.setLevel(logging.INFO)
ws_log.addFilter(QuietSuccess())  # a health check every 5 s is not a "rejection"
ws_log.addFilter(HandshakeLog())  # a port scan or a POST is one line, not a traceback
ws_log.addFilter(TicketScrub())  # a Foxglove ticket in a quoted request line never reaches a log

# Why small: the kernel socket buffer already holds plenty; bytes parked in asyncio's
# buffer cannot be dropped or superseded, bytes in our scheduler can (Pound, Robofleet n_T).
WRITE_LIMIT_BYTES = 16 * 1024
# Bytes the writer takes from the scheduler per transport write.
WRITE_BATCH_BYTES = 64 * 1024
REGISTRY_FLUSH_PERIOD_S = 1.0
# The opening handshake's bound (websockets' default): a client that has not completed
# its request by then (one byte a second) is cut, with one log line.
OPEN_TIMEOUT_S = 10.0


class ListenError(Exception):
    """A listener cannot bind; the message names the config field at fault (the port:
    ``listen_port`` or ``web.listen_port``; the address: ``listen_host`` or
    ``web.listen_host``), the address and the reason."""


# The bind failures that are the address's fault, not the port's: a name that does not
# resolve (socket.gaierror), an address this machine does not have.
_HOST_ERRNOS = frozenset({errno.EADDRNOTAVAIL, errno.EAFNOSUPPORT})


def _listen_field(exc: OSError, prefix: str) -> str:
    if isinstance(exc, socket.gaierror) or exc.errno in _HOST_ERRNOS:
        return f"{prefix}listen_host"
    return f"{prefix}listen_port"


class _Handshake(NamedTuple):
    """What the upgrade request said, kept on the connection until its handler runs."""

    peer: Peer
    identities: list[Identity]
    bad_token: bool
    writer: ConnectionWriter
    auth: AuthMap  # the map *identities* were matched against
    refusal: str | None = None  # why a Foxglove ticket was refused


class _Request(NamedTuple):
    """A request read by ``process_request``, kept for ``process_response``."""

    upgrade: Upgrade
    identities: list[Identity]
    bad_token: bool
    auth: AuthMap
    refusal: str | None = None  # why a Foxglove ticket was refused
    # > 0: the request's address is over its failed-login budget and the request needs a
    # token (it carries one, or has no other identity): refused with 429, token unhashed
    retry_after_s: float = 0.0


class RelayServer:
    """A running relay.

    Args:
        config: Server config; ``listen_port`` 0 picks a free port (see :attr:`port`).
        auth: Auth map; read from ``config.auth_map`` when ``None``. Either way the file
            is watched from :meth:`start` on and reloaded when it changes.
    """

    def __init__(self, config: ServerConfig, auth: AuthMap | None = None) -> None:
        self.config = config
        auth = auth if auth is not None else load_auth_map(config.auth_map)
        self.metrics = Metrics()
        self.registry = _registry(config)
        recording = config.recording
        if recording is not None and config.cluster is not None:  # sharded by replica
            recording = dataclasses.replace(recording, file_label=config.cluster.name)
        self.recorder = (None if recording is None else
                         Recorder(recording, max_message_bytes=config.limits.max_frame_bytes,
                                  msg_types=config.msg_types))
        self.core = RelayCore(config, auth, self.registry, self.metrics,
                              recorder=self.recorder)
        if self.recorder is not None:
            self.recorder.latched_source = self.core.latched.local_messages
        if config.cluster is not None:  # the only place that knows about replicas
            from fleetctl.server.cluster.natsfanout import NatsFanout
            from fleetctl.server.cluster.remoteinterest import RemoteInterest
            from fleetctl.server.cluster.sharedlatched import SharedLatched
            from fleetctl.server.cluster.sharedregistry import SharedRegistry
            from fleetctl.server.cluster.sharedsessions import SharedSessions

            assert isinstance(self.registry, SharedRegistry)
            latched = SharedLatched(config.cluster, self.core.latched,
                                    functools.partial(firstframes.sender_may_send, self.core))
            sessions = SharedSessions(config.cluster, config.limits.session_expiry_s,
                                      self.core.on_remote)
            self.core.use_shared_sessions(sessions)
            self.core.use_fanout(NatsFanout(
                self.core.local, self.core.on_remote, config.cluster, self.registry, latched,
                functools.partial(firstframes.on_remote_keyframe_request, self.core),
                sessions, RemoteInterest(config.cluster)))
        self.recordings = (RecordingsEndpoint(self.recorder) if self.recorder is not None
                           else None)
        self.reloader = AuthReloader(config.auth_map, self.core.reload_auth, self.metrics)
        # The fleet's own message types (server.yaml msg_types) for the parts that decode.
        self.codec = codec_for(config.msg_types)
        self.foxglove = FoxgloveAdapter(self.core, WRITE_BATCH_BYTES, codec=self.codec)
        self.write_through = WriteThrough()
        self._server: Server | None = None
        self._web_server: Server | None = None
        self._page: WebPage | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._background: list[asyncio.Task[None]] = []
        self._flushing: asyncio.Future[None] | None = None
        proxies = config.trusted_proxies
        self.gate = UnauthenticatedGate(
            config.limits.max_unauthenticated_connections,
            config.limits.max_unauthenticated_per_address,
            exempt=lambda a: within(parse_address(a), proxies),
            refused=self.metrics.connections_refused)
        self._warned_proxy = False

    @property
    def auth(self) -> AuthMap:
        """The auth map in force (replaced by each successful reload)."""
        return self.core.auth

    @property
    def port(self) -> int:
        """The bound TCP port of the relay listener (its first address)."""
        return self.addresses[0][1]

    @property
    def addresses(self) -> list[tuple[str, int]]:
        """``(host, port)`` of every relay socket (one per ``listen_host`` address)."""
        assert self._server is not None, "server not started"
        return _addresses(self._server)

    @property
    def url(self) -> str:
        """``ws://host:port/`` (``wss`` with TLS) of the first relay socket."""
        scheme = "wss" if self.config.tls_cert else "ws"
        return _url(scheme, *self.addresses[0]) if self._server else f"{scheme}://?/"

    @property
    def web_addresses(self) -> list[tuple[str, int]]:
        """``(host, port)`` of every web listener socket (empty without ``web:``)."""
        return _addresses(self._web_server) if self._web_server is not None else []

    @property
    def web_port(self) -> int:
        """The bound TCP port of the web listener (its first address)."""
        assert self._web_server is not None, "no web listener"
        return self.web_addresses[0][1]

    @property
    def web_url(self) -> str | None:
        """``https://host:port/`` of the page on the web listener, or ``None``."""
        addresses = self.web_addresses
        return _url("https", *addresses[0]) if addresses else None

    async def start(self) -> None:
        """Bind and start serving; start watching the auth map.

        Raises:
            ConfigError: A certificate or key cannot be loaded, or the recording
                directory cannot be created.
            ListenError: An address cannot be bound.
            ClusterStartError: With ``cluster:``, NATS cannot be joined.
        """
        config, web = self.config, self.config.web
        main_ssl = (server_context(config.tls_cert, config.tls_key)
                    if config.tls_cert is not None and config.tls_key is not None else None)
        web_ssl = server_context(web.tls_cert, web.tls_key) if web is not None else None
        if self.recorder is not None:
            _start_recorder(self.recorder)
        try:
            await self.core.fanout.start()  # NATS first: no connection before it is up
            self._server = await self._listen(config.listen_host, config.listen_port, main_ssl,
                                              web=False, prefix="")
            if web is not None:
                self._page = web_page(web, self.codec.registry)
                self._web_server = await self._listen(web.listen_host, web.listen_port,
                                                      web_ssl, web=True, prefix="web.")
        except BaseException:
            await self.stop()
            raise
        self._background = [asyncio.create_task(self._flush_registry()),
                            asyncio.create_task(self.reloader.watch())]
        log.info("relay listening on %s", ", ".join(
            _url("wss" if main_ssl else "ws", *a) for a in self.addresses))
        if self._web_server is not None:
            log.info("web page and relay listening on %s", ", ".join(
                _url("https", *a) for a in self.web_addresses))

    async def stop(self) -> None:
        """Close every connection (1001), stop listening, flush the registry."""
        for task in self._background:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._background = []
        if self._flushing is not None:  # a write in a worker thread: let it finish
            with contextlib.suppress(Exception):
                await self._flushing
        for server in (self._server, self._web_server):
            if server is not None:
                server.close(close_connections=True)
                await server.wait_closed()
        for task in list(self._tasks):
            task.cancel()
        await self.core.fanout.stop()
        self.core.sessions.flush()
        self.registry.close()
        if self.recorder is not None:  # after the listeners: the last frames are written
            self.recorder.detach()
            await asyncio.get_running_loop().run_in_executor(None, self.recorder.stop)

    def reload_auth(self, reason: str = "reload requested") -> bool:
        """Reload the auth map file now (SIGHUP does this); see :class:`AuthReloader`.

        Returns:
            Whether the new map is in force (an invalid file keeps the previous one).
        """
        return self.reloader.reload(reason)

    async def _listen(self, hosts: Hosts, port: int, ssl_context: ssl.SSLContext | None, *,
                      web: bool, prefix: str) -> Server:
        def respond(connection: ServerConnection, request: Request,
                    response: Response) -> None:
            self._process_response(connection, request, response, by_address=not web)

        try:
            return await serve(
                self._handler,
                # asyncio's create_server binds every address of a sequence; websockets
                # passes the value through but annotates it as one string.
                cast(str, host_list(hosts)),
                port,
                # The gate argument goes to RelayConnection; websockets' annotation is a type.
                create_connection=cast(Any, functools.partial(
                    RelayConnection, gate=self.gate, metrics=self.metrics,
                    known=None if web else self._address_identity)),
                process_request=self._web_request if web else self._process_request,
                process_response=respond,
                select_subprotocol=self.foxglove.select_subprotocol,
                max_size=self.config.limits.max_frame_bytes,
                open_timeout=OPEN_TIMEOUT_S,
                max_queue=16,
                write_limit=WRITE_LIMIT_BYTES,
                ssl=ssl_context,
                logger=ws_log,
                # Inbound permessage-deflate only: robots deflate their small messages;
                # the relay never compresses what it sends (fleetctl.linkdeflate).
                compression=None,
                extensions=[RelayDeflateFactory()],
            )
        except OSError as exc:
            field = _listen_field(exc, prefix)
            raise ListenError(f"field {field!r}: cannot listen on {hosts_text(hosts)}:{port}: "
                              f"{exc.strerror or exc}") from None

    def _address_identity(self, address: str) -> bool:
        """Whether a TCP peer's address is an ``ip``/``cidr`` identity of the auth map in
        force (on the relay port, such a connection is authenticated by its address)."""
        return bool(self.core.auth.match_address(parse_address(address)))

    async def __aenter__(self) -> RelayServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def _flush_registry(self) -> None:
        while True:  # periodic write-behind and session expiry, not synchronization
            await asyncio.sleep(REGISTRY_FLUSH_PERIOD_S)
            self.core.sessions.expire()
            self.metrics.forget_idle(asyncio.get_running_loop().time())
            jobs: list[Callable[[], object]] = [
                j for j in (self.registry.take_flush(), self.core.sessions.take_changes())
                if j is not None]
            if not jobs:
                continue
            # SQLite commits (an fsync each) run in a worker thread: the relay goes on.
            # Both jobs share the registry's connection: one worker call, one at a time.
            self._flushing = asyncio.get_running_loop().run_in_executor(
                None, _run_jobs, jobs)
            try:
                await asyncio.shield(self._flushing)
            except asyncio.CancelledError:
                raise
            except Exception:  # a full disk must not stop the relay
                log.exception("robot registry flush failed")
            self._flushing = None

    # -- handshake ----------------------------------------------------------------------

    def _read(self, connection: ServerConnection, request: Request,
              by_address: bool) -> _Request:
        """Read *request*'s sender and resolve its identities (never raises but
        :class:`BadRequest`); kept on the connection for ``process_response``."""
        upgrade = read_request(connection, request, self.config.trusted_proxies)
        if upgrade.proxied_loopback and not self._warned_proxy:
            self._warned_proxy = True
            log.warning("a request from loopback carries a proxy header (%s) but loopback "
                        "is not in trusted_proxies: such requests get no loopback "
                        "privilege on /robots and /metrics; if a reverse proxy runs on "
                        "this host, list 127.0.0.1 in trusted_proxies",
                        "/".join(PROXY_HEADERS))
        auth = self.core.auth
        foxglove = self.foxglove.wanted(request)  # people: address identities do not apply
        identities = auth.match_address(upgrade.address) if by_address and not foxglove else []
        wait_s = self._login_wait_s(upgrade, bool(identities), request)
        if wait_s > 0:  # before hashing anything: the address is over its budget
            parsed = _Request(upgrade, identities, False, auth, retry_after_s=wait_s)
            cast(RelayConnection, connection).relay_request = parsed
            return parsed
        bad = False
        if upgrade.token is not None:
            found = auth.match_token(upgrade.token)  # None for anything not a token
            bad = found is None
            identities = identities if found is None else [*identities, found]
            if bad:
                self._login_failed(upgrade, request)
        refusal = None
        if foxglove and wants_websocket(request):
            ticket, refusal = self.foxglove.redeem(request, self._secure(by_address), auth)
            identities = identities if ticket is None else [*identities, ticket]
        parsed = _Request(upgrade, identities, bad, auth, refusal)
        cast(RelayConnection, connection).relay_request = parsed
        return parsed

    def _login_wait_s(self, upgrade: Upgrade, by_address: bool, request: Request) -> float:
        """Seconds a request must wait for its address's failed-login budget, when it
        needs a token: it carries one, or it is an upgrade with no address identity
        (which can only authenticate by a token frame). 0: it goes on. A robot known by
        its address, the operator on loopback without a token and ``/healthz`` never
        wait."""
        if upgrade.token is None and (by_address or not wants_websocket(request)):
            return 0.0
        if request.path.split("?", 1)[0] == "/healthz":
            return 0.0
        wait_s = self.core.logins.retry_after_s(_text(upgrade.address))
        if wait_s > 0:
            self.core.logins.refused()
            self.metrics.count_error("login_throttled")
            self._log_login(upgrade, "request refused (429), token unhashed")
        return wait_s

    def _login_failed(self, upgrade: Upgrade, request: Request) -> None:
        self.core.logins.failed(_text(upgrade.address))
        upgrading = wants_websocket(request)
        if not upgrading:  # an upgrade's is counted with its error frame (login_refused)
            self.metrics.count_error("bad_token")
        kind = "WebSocket upgrade" if upgrading else "GET"
        self._log_login(upgrade, f"failed login (bad Bearer token on a {kind})")

    def _log_login(self, upgrade: Upgrade, what: str) -> None:
        line = self.core.logins.log_line(_text(upgrade.address), what)
        if line is not None:
            log.warning("%s", line)

    def _login_budget(self, connection: ServerConnection, request: Request) -> Response:
        """``GET /login-budget``: whether the caller's address is over its failed-login
        budget, for a page on any origin (:func:`endpoints.login_budget`). Answered before
        :meth:`_read`: a token on it is never hashed, and asking is no failed login."""
        try:
            upgrade = read_request(connection, request, self.config.trusted_proxies)
        except BadRequest as exc:
            return endpoints.text(http.HTTPStatus.BAD_REQUEST, f"{exc}\n")
        return endpoints.login_budget(self.core.logins.retry_after_s(_text(upgrade.address)))

    def _process_request(self, connection: ServerConnection, request: Request,
                         ) -> Response | Awaitable[Response] | None:
        path = request.path.split("?", 1)[0]
        if path == endpoints.LOGIN_BUDGET_PATH:
            return self._login_budget(connection, request)
        try:
            parsed = self._read(connection, request, by_address=True)
        except BadRequest as exc:
            return endpoints.text(http.HTTPStatus.BAD_REQUEST, f"{exc}\n")
        if path == "/healthz":
            return endpoints.text(http.HTTPStatus.OK, "ok\n")
        if parsed.retry_after_s > 0:
            return endpoints.too_many_logins(parsed.retry_after_s)
        if wants_websocket(request):
            return _http10_upgrade(connection)
        if path == TICKET_PATH:
            return self._ticket(parsed, request, by_address=True)
        if path == "/metrics":
            return self._metrics(parsed)
        if path == "/robots":
            return self._robots(parsed)
        if path == RECORDINGS_PATH or path.startswith(RECORDINGS_PATH + "/"):
            return self._recordings(parsed, path, request)
        return endpoints.text(http.HTTPStatus.NOT_FOUND, "not found: this port serves "
                              "WebSocket upgrades, /healthz, /metrics, /robots and "
                              "/recordings\n")

    def _web_request(self, connection: ServerConnection, request: Request,
                     ) -> Response | Awaitable[Response] | None:
        # The web listener: the page, /healthz, /login-budget and /recordings; /metrics and
        # /robots stay on the relay port (often not exposed to the internet).
        if request.path.split("?", 1)[0] == endpoints.LOGIN_BUDGET_PATH:
            return self._login_budget(connection, request)
        try:
            parsed = self._read(connection, request, by_address=False)
        except BadRequest as exc:
            return endpoints.text(http.HTTPStatus.BAD_REQUEST, f"{exc}\n")
        if parsed.retry_after_s > 0:
            return endpoints.too_many_logins(parsed.retry_after_s)
        if wants_websocket(request):
            return _http10_upgrade(connection)
        path = request.path.split("?", 1)[0]
        if path == TICKET_PATH:
            return self._ticket(parsed, request, by_address=False)
        if path == RECORDINGS_PATH or path.startswith(RECORDINGS_PATH + "/"):
            # People fetch recordings here (`fleetctl up` publishes only this port), with
            # a Bearer token: no loopback privilege on the port a reverse proxy on the
            # same host would make every caller's.
            if not parsed.identities:
                return _unauthorized(path, parsed.bad_token, token_only=True)
            return self._recordings(parsed, path, request)
        assert self._page is not None and self.config.web is not None
        return page_response(self._page, request, self.config.web.replica_ports)

    def _secure(self, by_address: bool) -> bool:
        """Whether a listener speaks TLS (the web listener always does)."""
        return not by_address or self.config.tls_cert is not None

    def _ticket(self, parsed: _Request, request: Request, by_address: bool) -> Response:
        return self.foxglove.ticket_response(parsed.auth, parsed.upgrade.token,
                                             self._secure(by_address),
                                             request.headers.get("Host"))

    def _caller(self, parsed: _Request) -> tuple[bool, Any]:
        """``(allowed, perms)`` of a /robots or /metrics caller (``perms`` ``None``: a
        local caller without identity, who sees everything)."""
        perms = self.core.pool.get(parsed.identities) if parsed.identities else None
        return endpoints.robots_allowed(parsed.upgrade.is_local, perms, parsed.bad_token)

    def _robots(self, parsed: _Request) -> Response:
        allowed, perms = self._caller(parsed)
        if not allowed:
            return _unauthorized("/robots", parsed.bad_token)
        return endpoints.json_response({"robots": self.core.robots_for(perms)})

    async def _recordings(self, parsed: _Request, path: str, request: Request) -> Response:
        # Who may list and fetch: the callers of /metrics, each file filtered by the
        # receive rules (fleetctl.server.recording.http).
        allowed, perms = self._caller(parsed)
        if not allowed:
            return _unauthorized("/recordings", parsed.bad_token)
        if self.recordings is None:
            return endpoints.text(http.HTTPStatus.NOT_FOUND, "this server records nothing "
                                  "(no recording: section in its config)\n")
        return await self.recordings.respond(path, request.headers, perms)

    def _metrics(self, parsed: _Request) -> Response:
        allowed, _ = self._caller(parsed)
        if not allowed:
            return _unauthorized("/metrics", parsed.bad_token)
        families = [*(self.recorder.metric_families() if self.recorder is not None else ()),
                    *self.foxglove.metric_families(),
                    *self.core.fanout.metric_families(),
                    ("fleetctl_standby_connections", "gauge", "Robots' standby connections "
                     "open (authenticated, one per session at most).", "",
                     {"": float(len(self.core.standbys))}),
                    *self._login_families()]
        text = self.metrics.render(self._gauges(), self.core.session_gauges(), families)
        return endpoints.response(http.HTTPStatus.OK, text.encode("utf-8", "backslashreplace"),
                                  endpoints.PROMETHEUS_CONTENT_TYPE)

    def _login_families(self) -> list[tuple[str, str, str, str, dict[str, float]]]:
        logins = self.core.logins
        return [("fleetctl_failed_login_addresses", "gauge", "Client addresses (IPv4, IPv6 "
                 f"/64) whose failed logins are remembered (at most {logins.max_addresses}).",
                 "", {"": float(len(logins))}),
                ("fleetctl_failed_login_evictions_total", "counter", "Addresses forgotten "
                 "while they still held failed logins, to keep the table within its bound.",
                 "", {"": float(logins.evicted)})]

    def _process_response(
        self, connection: ServerConnection, request: Request, response: Response,
        by_address: bool,
    ) -> None:
        if response.status_code != http.HTTPStatus.SWITCHING_PROTOCOLS:
            return
        assert isinstance(connection, RelayConnection)
        parsed: _Request = connection.relay_request
        upgrade = parsed.upgrade
        foxglove = self.foxglove.speaks(connection)
        writer = ConnectionWriter(self.write_through)
        peer = self.core.new_peer(
            str(upgrade.address) if upgrade.address else None, close=self._closer(connection),
            # The Foxglove adapter's own writer task waits on the event; it is not
            # written through.
            wake=writer.event.set if foxglove else writer.wake,
            session_name=upgrade.session_name, by_address=by_address and not foxglove,
            standby=upgrade.standby and not foxglove,
        )
        if not foxglove:
            writer.write_now = functools.partial(self._write_now, connection, peer)
            # This server takes standby connections (RelayCore.activate): a client opens
            # one only to a server that says so.
            response.headers[STANDBY_HEADER] = "1"
        try:
            self._wire(connection, peer, parsed, writer)
        except BaseException:  # never leave a peer behind a failed handshake
            self.core.close_peer(peer)
            raise

    def _wire(self, connection: RelayConnection, peer: Peer, parsed: _Request,
              writer: ConnectionWriter) -> None:
        """Connect *peer* to *connection*: identities, frame sink, clean-up on loss."""
        # Only the hash of a token is kept (a reload re-checks the connection by it).
        peer.token_digests.update(i.token_sha256 for i in parsed.identities if i.token_sha256)
        connection.relay_state = _Handshake(peer, parsed.identities, parsed.bad_token, writer,
                                            parsed.auth, parsed.refusal)
        connection.relay_request = None
        max_frame_bytes = self.config.limits.max_frame_bytes
        peer.on_authenticated = lambda: connection.authenticated(max_frame_bytes)
        peer.throttle = lambda delay_s: connection.throttle(delay_s, peer)
        if peer.standby:
            # No keepalive pings while standby: the robot keeps the connection free of
            # unacknowledged data so that its first write after a cut leaves at once, and
            # a server ping sent into the cut would hold back every server frame after
            # the activation (pongs, the session) until TCP retransmitted it. websockets
            # starts the keepalive after this hook; it starts on activation instead.
            interval, connection.ping_interval = connection.ping_interval, None

            def start_keepalive() -> None:
                connection.ping_interval = interval
                connection.start_keepalive()

            peer.on_activated = start_keepalive
        core = self.core

        def sink(frame: bytes) -> bool:
            if peer.perms is None:
                return False  # not authenticated yet: keep order with the token frame
            if not peer.closing:
                try:
                    if not core.on_binary(peer, frame, hold=True):
                        connection.decline()  # over a rate: it and what follows wait
                except Exception as exc:  # as _handle: the frame's, not the connection's
                    self._not_handled(peer, exc)
            return True

        connection.frame_sink = sink
        connection.write_through = self.write_through
        connection.on_lost = lambda: core.close_peer(peer)
        if core.store_acks is not None:  # a cluster: a pong means "stored"
            connection.held_pongs = HeldPongs(connection, core.store_acks,
                                              lambda: peer.store_mark)
        if self.foxglove.speaks(connection):
            self.foxglove.wire(connection, peer)  # its own sink: Foxglove binary messages

    def _closer(self, connection: RelayConnection) -> Callable[[int, str], None]:
        def close(code: int, reason: str) -> None:
            # What it sends from now on is discarded: no pong may say it was taken.
            connection.discard_from_now()
            # Called from inside data_received or the relay: close in a task, keep a ref.
            task = asyncio.get_running_loop().create_task(self._close(connection, code, reason))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

        return close

    async def _close(self, connection: RelayConnection, code: int, reason: str) -> None:
        state = connection.relay_state
        cut = state is None or state.peer.perms is None or code in _CUT_CODES
        if state is not None:
            # Let queued control frames (the error that explains the close) go first,
            # within ABORT_AFTER_S: a peer that does not read would hold the close.
            peer: Peer = state.peer
            texts = [f for _, f in peer.outbound.pop_batch(WRITE_BATCH_BYTES)
                     if isinstance(f, str)]
            if self.foxglove.speaks(connection):  # as Foxglove Status messages
                texts = self.foxglove.translate(texts)
            with contextlib.suppress(ConnectionClosed, TimeoutError):
                await asyncio.wait_for(connection.send_frames(texts), ABORT_AFTER_S)
        if cut:
            # Not read any further (RFC 6455 7.1.7): a client without an identity, or one
            # closed for flooding, went on sending through websockets' 10 s close
            # timeout, every frame parsed (4 of them: a 200 Hz pair's p99 153 ms).
            connection.abort_with(code, reason)
            return
        await connection.close(code, reason)

    # -- connection ---------------------------------------------------------------------

    async def _handler(self, connection: ServerConnection) -> None:
        assert isinstance(connection, RelayConnection)
        state: _Handshake = connection.relay_state
        peer, identities, bad_token = state.peer, state.identities, state.bad_token
        if state.auth is not self.core.auth:  # reloaded since the upgrade: match again
            identities = self.core.current_identities(peer)
        if self.foxglove.speaks(connection):
            await self.foxglove.serve(connection, peer, identities, state.refusal,
                                       state.writer.event)
            return
        writer = asyncio.create_task(self._write_loop(connection, peer, state.writer))
        try:
            if bad_token:  # counted and logged when the request was read
                self.core.login_refused(peer, protocol.CLOSE_BAD_TOKEN, "bad_token",
                                        "unknown token", "bad token", None)
            elif identities:
                self.core.authenticate(peer, identities)
            else:
                asyncio.get_running_loop().call_later(
                    self.config.limits.auth_timeout_s, self._auth_timeout, connection, peer
                )
            await self._read_loop(connection, peer)
        finally:
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await writer
            self.core.close_peer(peer)
            if connection.close_code == protocol.CLOSE_TOO_BIG:
                self.metrics.count_close(protocol.CLOSE_TOO_BIG)

    def _auth_timeout(self, connection: RelayConnection, peer: Peer) -> None:
        # Abort, not close: a graceful close would hold the connection (and whatever it
        # buffered) for websockets' close timeout too.
        if peer.perms is None and not peer.closing:
            peer.closing = True
            self.metrics.count_close(protocol.CLOSE_NO_IDENTITY)
            log.warning("%s aborted: no identity within %.0f s", peer.label,
                        self.config.limits.auth_timeout_s)
            connection.abort_with(protocol.CLOSE_NO_IDENTITY, "no identity: no token frame "
                                  "in time")

    async def _read_loop(self, connection: RelayConnection, peer: Peer) -> None:
        # Only text frames and fragmented binary messages arrive here; complete binary
        # frames went through the sink already.
        with contextlib.suppress(ConnectionClosed):
            async for message in connection:
                # Over a rate the relay takes it after the pause; later frames wait behind
                # it in websockets' queue, which stops reading when full.
                while not peer.closing and not self._handle(peer, message):
                    if not await connection.throttle_ended():
                        return
                connection.message_handled()

    def _handle(self, peer: Peer, message: str | bytes) -> bool:
        """One text frame or fragmented binary message; ``False``: not taken yet, offer it
        again once the connection's throttle ends (RelayCore.on_binary's *hold*). A bug
        the frame triggers costs the frame (an error frame, one log line with the
        traceback), never the connection."""
        try:
            if isinstance(message, str):
                return self.core.on_text(peer, message, hold=True)
            return self.core.on_binary(peer, message, hold=True)
        except Exception as exc:
            self._not_handled(peer, exc)
            return True

    def _not_handled(self, peer: Peer, exc: Exception) -> None:
        """A bug a frame triggered: one log line with the traceback, one error frame.
        Without this, a frame taken in ``data_received`` (the sink) that raised made
        asyncio drop the whole connection ("protocol.data_received() call failed")."""
        log.error("%s: frame not handled", peer.label, exc_info=exc)
        self.core.send_error(peer, "malformed_frame", None,
                             f"the server could not handle this frame ({type(exc).__name__})")

    async def _write_loop(
        self, connection: RelayConnection, peer: Peer, writer: ConnectionWriter
    ) -> None:
        outbound, wake = peer.outbound, writer.event
        with contextlib.suppress(ConnectionClosed):
            while True:
                if not len(outbound):
                    wake.clear()
                    writer.idle = True  # from here on frames may be written through
                    try:
                        await wake.wait()
                    finally:
                        writer.idle = False
                    if not len(outbound):
                        continue  # written through meanwhile
                await connection.send_frames(self._pop_counted(outbound))
                mark = outbound.ack_mark()  # None unless the peer has a session
                if mark is not None:
                    await self._ack_point(connection, outbound, mark)

    def _write_now(self, connection: RelayConnection, peer: Peer) -> bool:
        """One batch of *peer*'s queue written synchronously, as :meth:`_write_loop`
        would (see :mod:`fleetctl.server.writethrough`); True when the queue is empty
        afterwards, False when it could not write or more is queued."""
        outbound = peer.outbound
        if peer.closing or not connection.can_write_now():
            return False
        frames = self._pop_counted(outbound)
        mark = outbound.ack_mark()  # None unless the peer has a session
        waiter = connection.write_frames_now(
            frames, None if mark is None else mark.to_bytes(8, "big"))
        if waiter is not None and mark is not None:
            waiter.add_done_callback(functools.partial(_on_pong, outbound, mark))
        self.write_through.written += 1
        return not len(outbound)

    def _pop_counted(self, outbound: OutboundScheduler) -> list[bytes | str]:
        """One batch of *outbound*'s frames, counted as sent (both writers' first step)."""
        batch = outbound.pop_batch(WRITE_BATCH_BYTES)
        metrics = self.metrics
        for topic, frame in batch:
            metrics.count_out(topic, len(frame))
        return [frame for _, frame in batch]

    @staticmethod
    async def _ack_point(connection: RelayConnection, outbound: OutboundScheduler,
                         mark: int) -> None:
        """Ping after session no_drop frames: the pong (the client answers pings in order,
        after reading what came before) acknowledges them (see OutboundScheduler)."""
        waiter = asyncio.ensure_future(await connection.ping(mark.to_bytes(8, "big")))
        waiter.add_done_callback(functools.partial(_on_pong, outbound, mark))

    def _gauges(self) -> list[tuple[str, str, dict[str, float]]]:
        peers = self.core.peers.values()
        depth = {p.metric_label: float(len(p.outbound)) for p in peers}
        nbytes = {p.metric_label: float(p.outbound.queued_bytes) for p in peers}
        dropped = {p.metric_label: float(p.outbound.dropped_total) for p in peers}
        return [
            ("fleetctl_outbound_queue_frames", "Frames queued per connection.", depth),
            ("fleetctl_outbound_queue_bytes", "Bytes queued per connection.", nbytes),
            ("fleetctl_outbound_dropped", "Frames dropped per open connection.", dropped),
        ]


# Server closes after which the connection is not read any further (see _close): bad
# input in a row, and floods (subscription refusals past the bound, one connection too
# many for the identity).
_CUT_CODES = frozenset({protocol.CLOSE_MALFORMED, protocol.CLOSE_SUBSCRIPTION_FLOOD,
                        protocol.CLOSE_TOO_MANY})


def _unauthorized(path: str, bad_token: bool, token_only: bool = False) -> Response:
    """401 for a caller that :func:`endpoints.robots_allowed` refused, saying why
    (*token_only*: on the web listener, where only a Bearer token identifies a caller)."""
    if bad_token:
        why = "the Bearer token matches no user or robot of this fleet"
    elif token_only:
        why = "needs a Bearer token of this fleet (Authorization: Bearer TOKEN)"
    else:
        why = ("needs a fleet identity (a robot's or user's address, or a Bearer token) or a "
               "loopback caller")
    return endpoints.text(http.HTTPStatus.UNAUTHORIZED, f"GET {path}: {why}\n")


def _http10_upgrade(connection: ServerConnection) -> Response | None:
    """400 for a WebSocket upgrade sent as HTTP/1.0 (RFC 6455 4.1 needs HTTP/1.1; the
    server reads HTTP/1.0 for its plain GETs only, :mod:`fleetctl.server.http10`), else
    ``None``: go on with the handshake."""
    if not cast(RelayConnection, connection).http10:
        return None
    return endpoints.text(http.HTTPStatus.BAD_REQUEST,
                          "a WebSocket upgrade needs HTTP/1.1 (RFC 6455 4.1)\n")


def _text(address: object | None) -> str | None:
    return None if address is None else str(address)


def _on_pong(outbound: OutboundScheduler, mark: int, waiter: asyncio.Future[float]) -> None:
    # A closed connection fails its waiters: then take_no_drop() keeps the frames.
    if not waiter.cancelled() and waiter.exception() is None:
        outbound.acked(mark)


def _start_recorder(recorder: Recorder) -> None:
    try:
        recorder.start()
    except OSError as exc:
        raise ConfigError(f"field 'recording.directory': cannot create "
                          f"{recorder.config.directory}: {exc.strerror or exc}") from None


def _run_jobs(jobs: list[Callable[[], object]]) -> None:
    for job in jobs:
        job()


def _addresses(server: Server) -> list[tuple[str, int]]:
    return [tuple(s.getsockname()[:2]) for s in server.sockets]  # type: ignore[misc]


def _url(scheme: str, host: str, port: int) -> str:
    return f"{scheme}://{f'[{host}]' if ':' in host else host}:{port}/"


async def run_server(config: ServerConfig, ready: Callable[[RelayServer], None] | None = None,
                     stop: asyncio.Event | None = None) -> None:
    """Run until SIGTERM/SIGINT (or *stop* is set), then shut down gracefully.

    SIGHUP reloads the auth map (:meth:`RelayServer.reload_auth`).

    Args:
        config: The server config.
        ready: Called with the started server (e.g. to print the URL), once SIGHUP is
            handled.
        stop: Optional event that stops the server when set.
    """
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    async with RelayServer(config) as server:
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(signal.SIGHUP, server.reload_auth, "SIGHUP")
        try:
            if ready is not None:
                ready(server)
            await stop.wait()
            log.info("shutting down")
        finally:
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.remove_signal_handler(signal.SIGHUP)


def _registry(config: ServerConfig) -> RobotRegistry:
    """The robot registry: SQLite alone, or shared with the other replicas on NATS."""
    offline_after_s = config.limits.robot_offline_after_s
    if config.cluster is None:
        return RobotRegistry(config.database, offline_after_s)
    from fleetctl.server.cluster.sharedregistry import SharedRegistry

    return SharedRegistry(config.database, offline_after_s, config.cluster)
