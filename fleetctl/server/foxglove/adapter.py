"""The asyncio side of the Foxglove protocol: handshake, tickets, reader and writer.

:class:`FoxgloveAdapter` is created once per :class:`~fleetctl.server.app.RelayServer`.
The server asks it:

- during the opening handshake: whether the client chose ``foxglove.websocket.v1``
  (:meth:`select_subprotocol`, :meth:`wanted`) and who a ticket in the query string
  names (:meth:`redeem`);
- for ``GET /foxglove/ticket``: a ticket for the Bearer token's identity
  (:meth:`ticket_response`);
- once the connection is open: to run it (:meth:`wire`, then :meth:`serve`).

Why ``GET`` and not ``POST``: websockets' HTTP parser takes only ``GET`` requests (the
port is a WebSocket port). The request is harmless to repeat, carries the token in a
header (a page of another origin cannot add it without a CORS preflight, which this port
never answers), and the answer is ``Cache-Control: no-store``.
"""

from __future__ import annotations

import asyncio
import contextlib
import http
import logging
import re
import time
import urllib.parse
from collections import OrderedDict
from collections.abc import Sequence

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response
from websockets.typing import Subprotocol

from fleetctl.server import endpoints, protocol
from fleetctl.server.authmap import AuthMap, Identity
from fleetctl.server.connection import RelayConnection
from fleetctl.server.foxglove import messages as fx
from fleetctl.server.foxglove import offload
from fleetctl.server.foxglove.catalog import TopicCatalog
from fleetctl.server.foxglove.tickets import TicketBook, TicketBookFull
from fleetctl.server.foxglove.transcode import SharedTranscoder
from fleetctl.server.foxglove.viewer import Viewer
from fleetctl.server.outbound import CONTROL_TOPIC
from fleetctl.server.peer import Peer
from fleetctl.server.relay import RelayCore
from fleetctl.wire.codec import Codec, default_codec

log = logging.getLogger("fleetctl.server.foxglove")

TICKET_PATH = "/foxglove/ticket"
# Seconds a channel stays advertised after the last connection sending it closed. A robot
# taking over its standby connection sends again within milliseconds, one reconnecting
# after a short outage within a few seconds (the relay calls a robot offline after 5 s):
# both keep their channels, and every viewer its subscriptions. A robot gone for good
# leaves its channels in the topic list this much longer.
CHANNEL_LINGER_S = 10.0
# Topics whose superseded frames were logged (once each); the oldest is forgotten past
# this (it may be said again), so a relay of many topics keeps bounded memory.
MAX_SUPERSEDED_TOPICS_SAID = 1024
_TICKET_RE = re.compile(r"([?&]ticket=)[^&#\s]*")


class FoxgloveAdapter:
    """The Foxglove protocol of one relay server.

    Args:
        core: The relay core (its catalog tap is set here).
        write_batch_bytes: Bytes a writer takes from a scheduler per transport write.
        tickets: The ticket book (default: 60 s tickets, bounded).
        codec: Decodes frames and gives schemas (the server's, with the fleet's own
            message types); ``None``: :func:`default_codec`.
    """

    def __init__(self, core: RelayCore, write_batch_bytes: int,
                 tickets: TicketBook | None = None, codec: Codec | None = None) -> None:
        self.core = core
        self.write_batch_bytes = write_batch_bytes
        self.codec = codec or default_codec()
        max_bytes = core.limits.max_frame_bytes
        self.catalog = TopicCatalog(self.codec, max_bytes, linger_s=CHANNEL_LINGER_S)
        self.transcoder = SharedTranscoder(self.codec, max_bytes)
        self.tickets = tickets if tickets is not None else TicketBook()
        self.viewers: dict[int, Viewer] = {}
        self.session_id = str(time.time_ns())
        self.convert_seconds = 0.0  # the conversion thread's time, for every viewer
        self.superseded = 0  # frames superseded in a viewer's queue while its batch converted
        self._superseded_said: OrderedDict[str, None] = OrderedDict()
        self.catalog.listeners.append(self._on_channel)
        core.catalog = self.catalog

    # -- handshake ----------------------------------------------------------------------

    @staticmethod
    def select_subprotocol(_connection: ServerConnection,
                           offered: Sequence[Subprotocol]) -> Subprotocol | None:
        """websockets' ``select_subprotocol``: Foxglove's when offered, else none (a
        fleetctl client offers none)."""
        return Subprotocol(fx.SUBPROTOCOL) if fx.SUBPROTOCOL in offered else None

    @staticmethod
    def wanted(request: Request) -> bool:
        """Whether *request* offers the Foxglove subprotocol."""
        return any(p.strip() == fx.SUBPROTOCOL for v in request.headers.get_all(
            "Sec-WebSocket-Protocol") for p in v.split(","))

    @staticmethod
    def speaks(connection: RelayConnection) -> bool:
        """Whether the open *connection* negotiated the Foxglove subprotocol."""
        return connection.subprotocol == fx.SUBPROTOCOL

    def redeem(self, request: Request, secure: bool,
               auth: AuthMap) -> tuple[Identity | None, str | None]:
        """Use the ``ticket`` of *request*'s query string; its identity as the auth map in
        force (*auth*) has it now (a token revoked since the ticket was issued: refused).

        Returns:
            ``(identity, None)``; ``(None, None)`` without a ticket; ``(None, reason)``
            for a ticket refused (unknown, used, expired, or not over TLS).
        """
        query = urllib.parse.urlsplit(request.path).query
        tickets = urllib.parse.parse_qs(query).get("ticket")
        if not tickets:
            return None, None
        # Over plain ws:// the ticket crossed the network in clear: burnt, and refused.
        identity = self.tickets.redeem(tickets[0], accept=secure)
        if not secure:
            return None, "tickets are accepted over TLS (wss://) only"
        if identity is None:
            return None, "ticket unknown, already used or expired: get a new one"
        digest = identity.token_sha256
        current = auth.match_digest(digest) if digest is not None else None
        if current is None:
            return None, "the token that asked for this ticket is no longer valid"
        return current, None

    def ticket_response(self, auth: AuthMap, token: str | None, secure: bool,
                        host: str | None) -> Response:
        """Answer ``GET /foxglove/ticket``: ``{"ticket", "expires_in_s", "url"}``.

        Args:
            auth: The auth map in force.
            token: The request's Bearer token, or ``None``.
            secure: The request came over TLS.
            host: The request's ``Host`` header (the URL to connect to), or ``None``.
        """
        if not secure:
            return endpoints.text(http.HTTPStatus.FORBIDDEN, "tickets are issued over TLS "
                                  "(https://) only: use the web listener or a TLS relay port\n")
        identity = auth.match_token(token) if token is not None else None
        if identity is None:
            return endpoints.text(http.HTTPStatus.UNAUTHORIZED,
                                  f"GET {TICKET_PATH} needs a valid Bearer token\n")
        try:
            ticket = self.tickets.issue(identity)
        except TicketBookFull as exc:
            return endpoints.text(http.HTTPStatus.SERVICE_UNAVAILABLE, f"{exc}\n")
        log.info("Foxglove ticket issued to %s (valid %.0f s, once)", identity.name,
                 self.tickets.ttl_s)
        url = f"wss://{host}/?ticket={ticket}" if host else None
        return endpoints.json_response({"ticket": ticket, "expires_in_s": self.tickets.ttl_s,
                                        "url": url})

    # -- connection ---------------------------------------------------------------------

    def wire(self, connection: RelayConnection, peer: Peer) -> None:
        """Give the open *connection* its viewer and binary frame sink (from the
        handshake's ``process_response``, before :meth:`serve` runs)."""
        viewer = Viewer(self.core, peer, self.catalog, self.codec, self.session_id)
        self.viewers[peer.peer_id] = viewer

        def sink(frame: bytes) -> bool:
            if peer.perms is None:
                return False  # not authenticated yet: the reader takes it, in order
            if not peer.closing:
                self._handle(viewer, frame)  # a bug costs a Status, not the connection
            return True

        connection.frame_sink = sink

    async def serve(self, connection: RelayConnection, peer: Peer, identities: list[Identity],
                    refusal: str | None, wake: asyncio.Event) -> None:
        """Run one Foxglove connection until it closes."""
        viewer = self.viewers[peer.peer_id]
        writer = asyncio.create_task(self._write_loop(connection, viewer, wake))
        try:
            if self._authenticate(viewer, identities, refusal):
                viewer.start()
            await self._read_loop(connection, viewer)
        finally:
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await writer
            self.viewers.pop(peer.peer_id, None)
            self.core.close_peer(peer)

    def _authenticate(self, viewer: Viewer, identities: list[Identity],
                      refusal: str | None) -> bool:
        peer, core = viewer.peer, self.core
        if refusal is not None or not identities:
            reason = refusal or (f"no identity: connect with ?ticket= (GET {TICKET_PATH} "
                                 "with a Bearer token issues one)")
            core.metrics.count_error("bad_token")
            peer.outbound.push_control(fx.status(fx.ERROR, reason))
            core.close_with(peer, protocol.CLOSE_BAD_TOKEN, reason[:120])
            return False
        return core.authenticate(peer, identities)

    async def _read_loop(self, connection: RelayConnection, viewer: Viewer) -> None:
        with contextlib.suppress(ConnectionClosed):
            async for message in connection:
                if not viewer.peer.closing:
                    self._handle(viewer, message)
                connection.message_handled()

    def _handle(self, viewer: Viewer, message: str | bytes) -> None:
        """One message; a bug it triggers costs a Status, never the connection."""
        peer = viewer.peer
        if peer.perms is None:
            return  # refused or closing: nothing it sends matters
        try:
            if isinstance(message, str):
                viewer.on_text(message)
            else:
                viewer.on_binary(message)
        except Exception as exc:
            log.exception("%s: Foxglove message not handled", peer.label)
            self.core.send_error(peer, "malformed_frame", None,
                                 f"the server could not handle this message "
                                 f"({type(exc).__name__})")

    async def _write_loop(self, connection: RelayConnection, viewer: Viewer,
                          wake: asyncio.Event) -> None:
        outbound, metrics = viewer.peer.outbound, self.core.metrics
        with contextlib.suppress(ConnectionClosed):
            while True:
                if not len(outbound):
                    wake.clear()
                    await wake.wait()
                viewer.refresh()  # an auth reload may have changed what it may receive
                batch = outbound.pop_batch(self.write_batch_bytes)
                frames = [f for _, f in batch if isinstance(f, bytes)]
                total, drops = outbound.dropped_total, dict(outbound.drops)
                converted = await offload.convert(self.transcoder, frames)
                if converted.converted:
                    self._converted(viewer, converted, total, drops)
                results = iter(converted.results)
                out: list[bytes | str] = []
                for topic, frame in batch:
                    data = (viewer.control(frame) if isinstance(frame, str)
                            else viewer.message(topic, next(results)))
                    if data is not None:
                        metrics.count_out(topic, len(data))
                        out.append(data)
                if out:
                    await connection.send_frames(out)

    def _converted(self, viewer: Viewer, batch: offload.Batch, total_before: int,
                   drops_before: dict[str, int]) -> None:
        """Count the thread's work for *viewer*'s batch and the frames its scheduler
        superseded meanwhile (the converter was slower than they came); say so once per
        topic."""
        self.convert_seconds += batch.seconds
        outbound = viewer.peer.outbound
        if outbound.dropped_total == total_before:
            return
        for topic, n in outbound.drops.items():
            new = n - drops_before.get(topic, 0)
            if new <= 0 or topic == CONTROL_TOPIC:
                continue
            self.superseded += new
            if topic in self._superseded_said:
                continue
            if len(self._superseded_said) >= MAX_SUPERSEDED_TOPICS_SAID:
                self._superseded_said.popitem(last=False)
            self._superseded_said[topic] = None
            log.warning("%s: Foxglove viewer: %d frame(s) of %s superseded while the relay "
                        "converted to CDR (%d frame(s) in %.0f ms): the viewer gets the "
                        "newest; counted in fleetctl_foxglove_superseded_total (said once "
                        "per topic)", viewer.peer.label, new, topic, batch.converted,
                        batch.seconds * 1e3)

    def metric_families(self) -> list[tuple[str, str, str, str, dict[str, float]]]:
        """``/metrics`` families (see :meth:`Metrics.render`): tickets, viewers, and the
        shared transcoder's work."""
        book, cache = self.tickets, self.transcoder
        return [
            ("fleetctl_foxglove_tickets_total", "counter", "Foxglove tickets by outcome "
             "(refused: unknown, used, expired or not over TLS).", "result",
             {"issued": book.issued, "redeemed": book.redeemed, "refused": book.refused}),
            ("fleetctl_foxglove_viewers", "gauge", "Foxglove connections open.", "",
             {"": len(self.viewers)}),
            ("fleetctl_foxglove_transcoded_total", "counter", "Frames converted to CDR for "
             "Foxglove viewers (once per frame; hit: served from the shared cache, failed: "
             "did not convert).", "result",
             {"converted": cache.transcoded - cache.failed, "hit": cache.hits,
              "failed": cache.failed}),
            ("fleetctl_foxglove_convert_seconds_total", "counter", "Seconds the conversion "
             "thread spent converting frames to CDR for Foxglove viewers (off the event "
             "loop).", "", {"": self.convert_seconds}),
            ("fleetctl_foxglove_superseded_total", "counter", "Frames superseded by newer "
             "ones in a Foxglove viewer's queue while its previous frames converted to CDR "
             "(the converter slower than they came; also in fleetctl_drops_total).", "",
             {"": self.superseded}),
        ]

    @staticmethod
    def translate(texts: list[str]) -> list[str]:
        """Control texts of a scheduler as a Foxglove connection gets them
        (:meth:`Viewer.control`): for the last words before a close."""
        return [t for t in map(Viewer.control, texts) if t is not None]

    def _on_channel(self, channel: fx.Channel, added: bool) -> None:
        for viewer in self.viewers.values():
            viewer.on_channel(channel, added)


class TicketScrub(logging.Filter):
    """Redact ``ticket=...`` from log records (a handshake error can quote the request
    line; a ticket must never reach a log)."""

    def filter(self, record: logging.LogRecord) -> bool:
        """Rewrite the record's message in place; never drops it."""
        text = record.getMessage()
        if "ticket=" in text:
            record.msg = _TICKET_RE.sub(r"\1<redacted>", text)
            record.args = None
        return True
