"""A websockets server connection tuned for relaying (the thin I/O layer of the relay).

Two departures from :class:`websockets.asyncio.server.ServerConnection`, both for the
hot path:

- complete binary frames go straight from ``data_received`` to ``frame_sink``
  (synchronously, no queue, no task switch; :class:`~fleetctl.frame_sink.FrameSink`,
  shared with the client). Text frames, fragmented messages, pings and close frames take
  the normal path (``recv()`` / the protocol).
- ``send_frames`` serializes a batch of frames and hands the transport one buffer,
  instead of one ``write()`` (often one syscall) per frame (from
  :class:`~fleetctl.batched_connection.BatchedWritesConnection`, shared with the client).

Before authentication the connection is small (docs/security.md): it holds a slot of
the server's :class:`~fleetctl.server.admission.UnauthenticatedGate` (no slot: aborted at
accept) and its frames and messages may be at most :data:`PRE_AUTH_MAX_FRAME_BYTES`
(websockets checks ``max_size`` per frame and over the fragments of a message). The
relay calls :meth:`RelayConnection.authenticated` to lift both.

Flow control is unchanged: ``send_frames`` waits while the transport's write buffer is
above ``write_limit``, so a writer never queues more than that in the kernel-facing
buffer; everything else waits in the per-connection
:class:`~fleetctl.server.outbound.OutboundScheduler`, where it can be dropped.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any

from websockets.asyncio.server import ServerConnection
from websockets.frames import DATA_OPCODES, CloseCode, Frame, Opcode
from websockets.protocol import Event, State

from fleetctl.batched_connection import BatchedWritesConnection
from fleetctl.frame_sink import FrameSink
from fleetctl.server.admission import UnauthenticatedGate
from fleetctl.server.heldpongs import HeldPongs
from fleetctl.server.http10 import RequestLine
from fleetctl.server.metrics import Metrics
from fleetctl.server.writethrough import WriteThrough

# Why 8 KiB: before authentication a client may send only its token frame (at most 4096
# characters of JSON); frames or fragmented messages past this close with 1009.
PRE_AUTH_MAX_FRAME_BYTES = 8 * 1024
# Frames one fragmented message may have (before authentication, after). Why: websockets
# bounds a message's payload bytes (max_size), not its frames, and it keeps every frame of
# a message until the last one comes: empty continuation frames cost nothing against
# max_size and ~100 bytes of Python each (a client sending them at line rate grew the
# relay by 60 MB in 6 s, authenticated or not). No client of ours fragments messages at
# the WebSocket level (fleetctl fragments are messages of their own; browsers send one
# frame per message).
PRE_AUTH_MAX_MESSAGE_FRAMES = 64
MAX_MESSAGE_FRAMES = 4096
log = logging.getLogger("fleetctl.server")
ABORT_AFTER_S = 1.0
# Throttling a client over its control request rate (see RelayConnection.throttle): why
# these: a flooding client should cost a few frames per pause, an honest one that hit the
# limit once (a page subscribing to hundreds of topics) loses well under a second.
MIN_THROTTLE_S = 0.05
MAX_THROTTLE_S = 1.0
THROTTLE_MEMORY_S = 5.0
THROTTLED_READ_BYTES = 4096  # a peer that does not read our close frame is cut off after this
# Bytes read from a connection per event loop round (asyncio's default: 256 KiB). Why
# less: the frames of one read are relayed before the loop serves another connection, so
# a robot sending small frames as fast as it can held every other connection's frames
# for the time its 256 KiB took (~2,400 frames: 60-90 ms on a loaded 2-core host).
# With a robot flooding 50-byte frames beside a 200 Hz robot/viewer pair (2026-12-06,
# host loaded by other work), the pair's p50 was 158-164 ms with 256 KiB reads and
# 21-22 ms with 64 KiB; the flood's own rate did not change (15-18k frames/s).
READ_BYTES = 64 * 1024
_LOG_EVERY = 1000  # refusals are logged first, then every 1000th (counted in metrics)


# Bytes the kernel may hold not yet sent on a connection (TCP_NOTSENT_LOWAT). Why: a
# receiver slower than what the relay has for it (a browser drawing clouds in software, a
# viewer behind a slow downlink) keeps its TCP window nearly closed, and the kernel's send
# buffer, autotuned up to tcp_wmem's 4 MiB, fills with frames that nothing can supersede:
# 7.8 s of latency on the demo's page (docs/server.md, "Slow receivers"). Capped, the socket
# stops being writable, the transport's write limit holds the writer, and frames wait in
# the connection's OutboundScheduler, where a newer message of a topic replaces the older.
UNSENT_LIMIT_BYTES = 64 * 1024


def limit_unsent(transport: asyncio.BaseTransport, limit: int = UNSENT_LIMIT_BYTES) -> bool:
    """Cap the unsent bytes the kernel keeps for *transport*'s socket; False where the
    socket or the option is not there (not TCP, not Linux): the connection works as before."""
    sock = transport.get_extra_info("socket")
    option = getattr(socket, "TCP_NOTSENT_LOWAT", None)
    if sock is None or option is None or sock.family not in (socket.AF_INET, socket.AF_INET6):
        return False
    try:
        sock.setsockopt(socket.IPPROTO_TCP, option, limit)
    except OSError as exc:
        log.debug("TCP_NOTSENT_LOWAT not set: %s", exc)
        return False
    return True


class RelayConnection(FrameSink, BatchedWritesConnection, ServerConnection):
    """Server connection with a synchronous binary-frame sink and batched writes."""

    def __init__(self, *args: Any, gate: UnauthenticatedGate | None = None,
                 metrics: Metrics | None = None,
                 known: Callable[[str], bool] | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._gate = gate
        self._known = known
        self._metrics = metrics
        self.max_message_frames = PRE_AUTH_MAX_MESSAGE_FRAMES
        self._request_bytes = 0  # bytes received before the request was complete
        self._request_line = RequestLine()  # an HTTP/1.0 health check is read as HTTP/1.1
        self._held_pong: Frame | None = None  # see _send_frame
        self._identified = False  # see authenticated
        self._unidentified_pong: Frame | None = None  # see _send_frame
        self._read_pong: Frame | None = None  # see _send_frame
        self._discarding = False  # see discard_from_now
        # Back-pressure (see decline): data frames read but not yet taken, the first of
        # them declined by the relay; a decline of the frame being handled; the end of the
        # current pause, and a reader waiting for it.
        self._held: deque[Frame] = deque()
        self._declined = False
        self._resume: asyncio.TimerHandle | None = None
        self._unthrottled: asyncio.Future[bool] | None = None
        self._protocol_send_frame: Callable[[Frame], None] | None = None
        self._slot: str | None = None  # address holding an unauthenticated slot
        self._strikes = 0  # throttles in a row (see throttle)
        self.on_lost: Callable[[], None] | None = None
        self.relay_state: Any = None
        self.relay_request: Any = None  # from process_request to process_response
        # A cluster: pongs wait until the no_drop frames before their ping are stored.
        self.held_pongs: HeldPongs | None = None
        # Frames relayed while this connection's bytes are handled are written at the end
        # of that handling (fleetctl.server.writethrough).
        self.write_through: WriteThrough | None = None

    @property
    def http10(self) -> bool:
        """Whether the request came as HTTP/1.0 (see :mod:`fleetctl.server.http10`)."""
        return self._request_line.http10

    @property
    def _all_handled(self) -> bool:
        """Every frame read so far was handled: none waits for ``recv()`` nor is held over a
        rate (:meth:`decline`), so the pong of the last ping read may go."""
        return not self.pending_messages and not self._held

    def message_handled(self) -> None:
        """Mark one message from ``recv()`` as handled; pongs held behind it may go."""
        super().message_handled()
        if not self._all_handled:
            return
        if self.held_pongs is not None:
            self.held_pongs.settle()
        elif self._read_pong is not None:
            self._answer_read_pong()
            with contextlib.suppress(OSError, RuntimeError):  # a transport closing meanwhile
                self.send_data()

    def data_received(self, data: bytes) -> None:
        """websockets' ``data_received`` with the frames relayed before this connection's
        own output (pongs) is written: relayed frames are written first (see
        :mod:`fleetctl.server.writethrough`), a pong a few microseconds later."""
        if self.request is None:  # the opening handshake: see connection_lost
            self._request_bytes += len(data)
            data = self._request_line.feed(data)
            if not data:
                return  # the request line is incomplete: nothing to parse yet
        through = self.write_through
        collecting = through is not None and through.begin()
        protocol = self.protocol
        try:
            protocol.receive_data(data)
            self._take(protocol.events_received())
        finally:
            if collecting:
                assert through is not None
                through.end()
        if self._all_handled:
            self._answer_read_pong()  # the frames before its ping are handled now
        try:
            self.send_data()
        except Exception as exc:  # as websockets: the reader sees it, the loop goes on
            self.set_recv_exc(exc)
        if protocol.close_expected() and self.close_timeout is not None \
                and self.close_deadline is None:
            self.close_deadline = self.loop.time() + self.close_timeout
        # Pings read with these bytes are answered once every frame before them was
        # handled (a cluster: their pongs wait for those frames' store).
        if self.held_pongs is not None and self._all_handled:
            self.held_pongs.settle()

    # -- back-pressure -------------------------------------------------------------------

    def decline(self) -> None:
        """The relay did not take the binary frame being handled: its connection is over a
        rate of its identity set and throttled (``RelayCore.on_binary``'s *hold*). That
        frame and every data frame read after it wait here, in order, unread by the
        relay, and are offered again when the pause ends (:meth:`throttle`).

        Why not discard them: a pong says that everything before its ping was taken, and
        the robot's link forgets its no_drop messages on it; over the control request
        rate the relay discarded the rest of the read and answered the next ping (5 of 5
        no_drop frames after 300 subscriptions lost). Bounded: reading stops at once, so
        what waits is at most what one read brought (:data:`READ_BYTES`, then
        :data:`THROTTLED_READ_BYTES` while the client keeps flooding) and the frame it
        completed; TCP pushes back on the client, which loses nothing. Pings, pongs and
        the close frame are not held (websockets answered the ping already; its pong waits
        for the held frames, :meth:`_send_frame`)."""
        self._declined = True

    @property
    def held_bytes(self) -> int:
        """Payload bytes of the frames waiting now (see :meth:`decline`)."""
        return sum(len(frame.data) for frame in self._held)

    def _take(self, events: Iterable[Event]) -> None:
        """Process *events* in order; from a frame the relay declines on, hold the data
        frames (see :meth:`decline`)."""
        held = self._held
        for event in events:
            if held and isinstance(event, Frame) and event.opcode in DATA_OPCODES:
                held.append(event)
                continue
            self.process_event(event)
            if self._declined:  # only the sink declines, and it takes frames only
                assert isinstance(event, Frame)
                self._declined = False
                held.append(event)
        if held:
            self.transport.pause_reading()

    def _drain(self) -> bool:
        """Offer the held frames again, in order, until the relay declines one more or
        :data:`THROTTLED_READ_BYTES` were offered; ``True``: stopped for the latter.

        Why the bound: the frames of one read are handled before the loop serves another
        connection, and what waits here was offered one small read per pause before (the
        rest discarded). Offered all at once, the tokens an identity set's connections
        saved during a 1 s pause went in one go: 8 connections of one token subscribing
        4 KiB patterns put an honest 1000 Hz subscriber's p50 at 12.8 ms (3.5 ms before;
        benchmarks/subscription_churn.py, loaded host)."""
        held = self._held
        offered = 0
        while held:
            if offered >= THROTTLED_READ_BYTES:
                return True
            event = held.popleft()
            offered += len(event.data)
            self.process_event(event)
            if self._declined:
                self._declined = False
                held.appendleft(event)
                return False
        return False

    async def throttle_ended(self) -> bool:
        """Wait until the current pause of :meth:`throttle` ends (a reader whose message
        the relay declined: it offers it again then). ``False``: the connection was lost
        first."""
        if self.transport.is_closing():
            return False
        if self._unthrottled is None:
            self._unthrottled = self.loop.create_future()
        return await self._unthrottled

    def _end_throttle(self) -> None:
        """The pause is over: the waiting reader goes on, the held frames are offered
        again, and reading resumes unless the relay declined one more (a new pause runs)
        or websockets' queue is full (it resumes reading when drained)."""
        waiter, self._unthrottled = self._unthrottled, None
        if waiter is not None and not waiter.done():
            waiter.set_result(True)
        self._offer_held()

    def _offer_held(self) -> None:
        """Offer the held frames, one slice per event loop round (:meth:`_drain`); once
        none is left, answer the pong behind them and read again."""
        if self.transport.is_closing():
            return
        through = self.write_through
        collecting = through is not None and through.begin()
        try:
            more = self._drain()
        finally:
            if collecting:
                assert through is not None
                through.end()
        if more:  # the rest in the next round, after other connections' reads
            self.loop.call_soon(self._offer_held)
            return
        if self._held or self.protocol.state is not State.OPEN:
            return  # declined again: a new pause runs
        if not self.pending_messages:
            self._answer_read_pong()
            if self.held_pongs is not None:
                self.held_pongs.settle()
        with contextlib.suppress(OSError, RuntimeError):  # a transport closing meanwhile
            self.send_data()
        if not self.recv_messages.paused:
            self.transport.resume_reading()

    def too_many_frames(self) -> None:
        """Close with 1009 (see :attr:`FrameSink.max_message_frames`)."""
        protocol = self.protocol
        if protocol.state is not State.OPEN:
            return  # failed already; the rest of this read is discarded
        reason = f"a message in more than {self.max_message_frames} frames"
        peer = self.transport.get_extra_info("peername")
        log.warning("connection from %s closed 1009: %s", peer[0] if peer else "?", reason)
        if self._metrics is not None:
            self._metrics.count_close(CloseCode.MESSAGE_TOO_BIG)
        # Not read any further: a peer that sends this would go on sending.
        self.abort_with(CloseCode.MESSAGE_TOO_BIG, reason)

    def _send_frame(self, frame: Frame) -> None:
        """The protocol's ``send_frame``, except that a pong is held while the transport is
        above its write limit (the peer does not read what it is sent), and a newer one
        replaces it: RFC 6455 5.5.3 lets an endpoint answer only the latest of several
        pings, and a pong acknowledges earlier pings too. Why: websockets answers every
        ping as it parses it, outside any flow control, so a client pinging without
        reading made the relay buffer 40 MB of pongs in 8 s, before authentication too.
        The held pong goes when the transport drains (:meth:`resume_writing`).

        A connection without an identity gets no pong at all until it has one (below), and
        a pong waits until the frames read before its ping are handled, and goes only if
        they were taken (:meth:`discard_from_now`)."""
        send = self._protocol_send_frame
        assert send is not None
        if frame.opcode is not Opcode.PONG:
            send(frame)
            return
        if self._discarding:
            return  # see discard_from_now
        if not self._identified:
            # A pong says that what came before the ping was taken, and frames of a
            # connection with no identity yet are discarded if its token is refused: a
            # client that trusts pongs (the robot's link) forgot no_drop messages the
            # relay dropped. Sent by authenticated(), the latest one (RFC 6455 5.5.3):
            # a ping flood before the token costs one frame, not a write buffer of pongs.
            if self._unidentified_pong is not None and self._metrics is not None:
                self._metrics.pongs_coalesced += 1
            self._unidentified_pong = frame
            return
        if self.held_pongs is None:
            # websockets answers a ping as it parses it, before the frames read with it
            # (and any message still waiting for recv()) are handled, and handling them
            # may close the connection and discard the rest (too many malformed frames
            # in a row, a message in too many frames): answered by _answer_read_pong
            # once they are handled, the latest one (RFC 6455 5.5.3). In a cluster
            # HeldPongs settles it so before it comes here.
            if self._read_pong is not None and self._metrics is not None:
                self._metrics.pongs_coalesced += 1
            self._read_pong = frame
            return
        self._pong(frame)

    def _answer_read_pong(self) -> None:
        """Send the pong of the last ping read, now that what came before it is handled."""
        pong, self._read_pong = self._read_pong, None
        if pong is not None:
            self._pong(pong)

    def _pong(self, frame: Frame) -> None:
        """Send a pong whose ping's earlier frames were handled (the caller writes it),
        or hold it while the transport is above its write limit (see _send_frame)."""
        if self._discarding or self.protocol.state is not State.OPEN:
            return  # see discard_from_now; closing: nobody reads pongs any more
        if not self.paused:
            assert self._protocol_send_frame is not None
            self._protocol_send_frame(frame)
            return
        if self._held_pong is not None and self._metrics is not None:
            self._metrics.pongs_coalesced += 1
        self._held_pong = frame

    def discard_from_now(self) -> None:
        """The relay closes this connection and discards whatever still comes from it:
        no pong leaves from now on, held ones included.

        Why: a pong says that everything sent before its ping was taken, and the robot's
        link forgets its no_drop messages on it. Until the close frame is written (after
        the queued error frames, within ABORT_AFTER_S when the peer does not read)
        websockets went on answering pings: a token revoked by an auth map reload
        (4403), a session taken over (4409), too many malformed frames (1007) answered
        the ping after frames the relay had dropped, and the client lost them. A pong
        withheld costs a resend (receivers drop the duplicate); one sent wrongly, the
        message. After the close frame a client reads nothing (RFC 6455 1.4)."""
        self._discarding = True
        self._read_pong = self._held_pong = self._unidentified_pong = None
        self._held.clear()  # never taken now

    def resume_writing(self) -> None:
        """Below the write limit again: send the pong held meanwhile (see _send_frame)."""
        super().resume_writing()
        pong, self._held_pong = self._held_pong, None
        if pong is None or self._discarding or self.protocol.state is not State.OPEN:
            return
        assert self._protocol_send_frame is not None
        self._protocol_send_frame(pong)
        self.send_data()  # asyncio lets resume_writing write (the buffer may grow again)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        """Take an unauthenticated slot, or abort the connection when there is none."""
        super().connection_made(transport)
        protocol = self.protocol
        self._protocol_send_frame = protocol.send_frame
        # An instance attribute, which Protocol.recv_frame calls (as HeldPongs does, which
        # wraps this one in a cluster).
        protocol.send_frame = self._send_frame  # type: ignore[method-assign]
        limit_unsent(transport)
        self._set_read_bytes(None)
        if self._gate is None:
            return
        peer = transport.get_extra_info("peername")
        address = str(peer[0]) if peer else "?"
        self.protocol.max_size = PRE_AUTH_MAX_FRAME_BYTES
        if self._known is not None and self._known(address):
            # An address identity (a robot over WireGuard): authenticated by its address
            # at the upgrade, so it takes no slot, and a flood of strangers filling every
            # slot cannot keep the fleet's robots out.
            return
        refused = self._gate.admit(address)
        if refused is None:
            self._slot = address
            return
        count = self._gate.refused[refused]
        if count % _LOG_EVERY == 1:
            log.warning("connection from %s refused: %s unauthenticated connections at "
                        "their cap (%d refused so far)", address, refused.replace("_", " "),
                        count)
        self.transport.abort()

    def authenticated(self, max_size: int) -> None:
        """The connection has an identity: frames up to *max_size* bytes, messages of up
        to :data:`MAX_MESSAGE_FRAMES` frames, slot given back, and the pong of a ping that
        came before its token sent (see :meth:`_send_frame`)."""
        self.protocol.max_size = max_size
        self.max_message_frames = MAX_MESSAGE_FRAMES
        self._release()
        self._identified = True
        pong, self._unidentified_pong = self._unidentified_pong, None
        if pong is None:
            return
        if self.held_pongs is None and (self.pending_messages or self._held):
            self._read_pong = pong  # after the messages read with the token are handled
        elif self.protocol.state is State.OPEN:
            self._pong(pong)
            self.send_data()

    def abort_with(self, code: int, reason: str) -> None:
        """Fail the connection now (RFC 6455 7.1.7): one close frame, then the TCP
        connection is closed without waiting for the peer's close frame, and anything it
        sent or buffered is discarded (no close timeout holding memory). Aborted outright
        if the close frame cannot be written within :data:`ABORT_AFTER_S`."""
        transport = self.transport
        with contextlib.suppress(Exception):  # already closing: abort is enough
            self.protocol.fail(code, reason)
            self.send_data()  # over TLS this closes the transport already (no half-close)
            # Closed once only: a second close() makes Python < 3.11.4's TLS transport
            # forget its protocol, and the abort below (or websockets' own) then raises
            # a traceback into the log for every refused login (CPython gh-98539; the
            # server image runs Debian bookworm's 3.11.2).
            if not transport.is_closing():
                transport.close()
        asyncio.get_running_loop().call_later(ABORT_AFTER_S, transport.abort)

    def throttle(self, delay_s: float, peer: Any) -> None:
        """Stop reading for *delay_s* seconds, then clear ``peer.throttled``, offer the
        frames held meanwhile again (:meth:`decline`) and read again (the relay's rate
        limits, docs/security.md).

        Each further throttle within :data:`THROTTLE_MEMORY_S` doubles the pause (from
        :data:`MIN_THROTTLE_S` up to :data:`MAX_THROTTLE_S`), and meanwhile the socket is
        read :data:`THROTTLED_READ_BYTES` at a time (plain TCP), so a flooding client
        costs one small read and one refused request per pause, not work per frame.
        """
        self.transport.pause_reading()
        self._strikes += 1
        self._set_read_bytes(THROTTLED_READ_BYTES)
        pause_s = min(MAX_THROTTLE_S, max(delay_s, MIN_THROTTLE_S * 2 ** (self._strikes - 1)))
        strikes = self._strikes
        loop = asyncio.get_running_loop()
        if self._resume is not None:  # one pause at a time: the latest
            self._resume.cancel()

        def resume() -> None:
            self._resume = None
            peer.throttled = False
            self._end_throttle()

        def forgive() -> None:
            if self._strikes == strikes:  # no throttle since: a normal client again
                self._strikes = 0
                self._set_read_bytes(None)

        self._resume = loop.call_later(pause_s, resume)
        loop.call_later(pause_s + THROTTLE_MEMORY_S, forgive)

    def _set_read_bytes(self, nbytes: int | None) -> None:
        # asyncio's plain socket transport reads max_size bytes per recv (256 KiB); a
        # TLS transport has no such knob and relies on the pauses alone.
        transport = self.transport
        if hasattr(type(transport), "max_size"):
            transport.max_size = READ_BYTES if nbytes is None else nbytes  # type: ignore[attr-defined]

    def _release(self) -> None:
        slot, self._slot = self._slot, None
        if slot is not None and self._gate is not None:
            self._gate.release(slot)

    def connection_lost(self, exc: Exception | None) -> None:
        """Give back the slot; run :attr:`on_lost` once the TCP connection is gone."""
        if (self.request is None and self._request_bytes
                and self.protocol.handshake_exc is None):
            # Cut by websockets' open_timeout with a request still incomplete (a slowloris
            # client, a stalled proxy), which websockets does not log. A peer that sent
            # nothing (a port scan, a refused connection) still logs nothing.
            peer = self.transport.get_extra_info("peername")
            log.info("opening handshake failed: connection from %s cut with an incomplete "
                     "request (%d bytes in the handshake timeout)",
                     peer[0] if peer else "?", self._request_bytes)
        self._release()
        self._held.clear()
        if self._resume is not None:
            self._resume.cancel()
            self._resume = None
        waiter, self._unthrottled = self._unthrottled, None
        if waiter is not None and not waiter.done():
            waiter.set_result(False)
        super().connection_lost(exc)
        on_lost, self.on_lost = self.on_lost, None
        if on_lost is not None:
            on_lost()
