"""A websockets connection that writes a batch of frames in one transport write.

Both ends of a fleet link send many small frames (fragments, relayed telemetry).
websockets' ``send()`` costs a flow-control round through the event loop per frame and its
``send_data()`` one ``transport.write()`` (often one syscall) per chunk; :meth:`send_frames`
serializes a whole batch and :meth:`send_data` hands the transport every pending chunk at
once. Flow control is unchanged: ``send_context`` still waits while the transport's write
buffer is above ``write_limit``.

On the client side, large binary frames are serialized by
:func:`fleetctl.masked_frame.masked_binary_frame` (one pass over the payload instead of
websockets' three), and large chunks are written on their own instead of being joined
with their neighbours (one more pass saved). Small frames take websockets' own path (and
the uplink deflate of :mod:`fleetctl.linkdeflate`, which leaves large frames alone).

On the server side a binary frame is serialized once for all its receivers
(:func:`server_binary_frame`): the relay writes one relayed frame to each receiver in
turn, a server's frames are not masked and it compresses nothing it sends, so the bytes
are the same for every one of them. websockets' own path built them anew per receiver
(a ``Frame``, its checks, a ``BytesIO`` and two copies of the payload): in-process, warm,
one payload to 16 receivers took 23 us for a scan and 411 us for a 1 MB cloud that way,
3.8 and 29 us this way (docs/server.md).

The robot client (:class:`fleetctl.client.transport.LinkConnection`) and the relay
(:class:`fleetctl.server.connection.RelayConnection`) both derive from this class.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterable
from typing import cast

from websockets.asyncio.connection import Connection
from websockets.exceptions import ConcurrencyError
from websockets.protocol import Side, State

from fleetctl.linkdeflate import passes_through
from fleetctl.masked_frame import masked_binary_frame, unmasked_binary_header

# Frames from this size on are masked in one pass and written without joining: below it
# the per-call costs of numpy and of a separate write exceed the copy they save.
ONE_PASS_MIN_BYTES = 16 * 1024

# The last payload server_binary_frame serialized and its frame, as one tuple so that a
# reader sees a matching pair (the demo runs the relay and clients on threads of one
# process). Kept until the next one: at most one relayed message and its frame.
_last_server_frame: tuple[bytes, bytes] | None = None


def server_binary_frame(payload: bytes | bytearray | memoryview) -> bytes:
    """*payload* as an unmasked final binary frame; the same object again for the same
    ``bytes`` object (a relayed frame written to each of its receivers in turn). A
    mutable buffer is framed anew each time: it may have changed since."""
    global _last_server_frame
    last = _last_server_frame
    if last is not None and last[0] is payload:
        return last[1]
    frame = unmasked_binary_header(len(payload)) + payload
    if type(payload) is bytes:
        _last_server_frame = (payload, frame)
    return frame


class BatchedWritesConnection(Connection):
    """Connection with batched frame sends and coalesced transport writes."""

    async def send_frames(self, frames: Iterable[bytes | str],
                          ping: bytes | None = None) -> asyncio.Future[float] | None:
        """Send each item as one frame (``str`` as text, ``bytes`` as binary), in order,
        then a ping carrying *ping* if given, all in one transport round.

        Returns:
            With *ping*: the future of its pong, as ``Connection.ping`` returns it
            (its result is the round trip in seconds). Without: None.

        Raises:
            ConnectionClosed: The connection is closed or closing.
            ConcurrencyError: A ping with the same payload still waits for its pong.
        """
        async with self.send_context():
            return self._queue_frames(frames, ping)

    def can_write_now(self) -> bool:
        """True when :meth:`write_frames_now` may be used: the connection is open and its
        transport is below its write limit (nothing to wait for)."""
        return (self.protocol.state is State.OPEN and not self.paused
                and not self.transport.is_closing())

    def write_frames_now(self, frames: Iterable[bytes | str],
                         ping: bytes | None = None) -> asyncio.Future[float] | None:
        """:meth:`send_frames` without awaiting, for a caller outside a coroutine that has
        checked :meth:`can_write_now` (so there is no flow control to wait for).

        Raises:
            ConcurrencyError: A ping with the same payload still waits for its pong.
        """
        waiter = self._queue_frames(frames, ping)
        self.send_data()
        return waiter

    def _queue_frames(self, frames: Iterable[bytes | str],
                      ping: bytes | None) -> asyncio.Future[float] | None:
        """Serialize *frames* (and *ping*) into the protocol's output; the caller writes
        it (send_context's exit, or send_data)."""
        protocol = self.protocol
        # The state is OPEN (send_context or can_write_now checked) and nothing below
        # awaits, so it stays open. A frame no extension touches (the uplink deflate
        # leaves large ones alone) is exactly what serialize() would produce, so it can
        # be queued directly.
        # websockets' own path logs each frame when debugging: keep it then.
        direct = not protocol.expect_continuation_frame and not protocol.debug
        client = protocol.side is Side.CLIENT
        extensions = protocol.extensions
        for frame in frames:
            if isinstance(frame, str):
                protocol.send_text(frame.encode())
            elif (not direct or (client and len(frame) < ONE_PASS_MIN_BYTES)
                  or not passes_through(extensions, len(frame))):
                # A client's small frame is decided by its size alone: no extension call
                # on the robot's per-message path.
                protocol.send_binary(frame)
            elif client:
                protocol.writes.append(cast(bytes, masked_binary_frame(frame)))
            else:
                protocol.writes.append(server_binary_frame(frame))
        if ping is None:
            return None
        # As Connection.ping registers its waiter (websockets 13-15), so that the
        # connection's pong handling completes it and acknowledges earlier pings.
        if ping in self.pong_waiters:
            raise ConcurrencyError("already waiting for a pong with the same data")
        waiter: asyncio.Future[float] = self.loop.create_future()
        self.pong_waiters[ping] = (waiter, self.loop.time())
        protocol.send_ping(ping)
        return waiter

    def send_data(self) -> None:
        """Write pending protocol output; consecutive data chunks go in one write call."""
        pending: list[bytes] = []
        for data in self.protocol.data_to_send():
            if data:
                pending.append(data)
                continue
            self._flush(pending)
            # An empty chunk means "end of stream" (websockets' convention).
            if self.transport.can_write_eof():
                with contextlib.suppress(OSError, RuntimeError):
                    self.transport.write_eof()
            else:
                self.transport.close()
        self._flush(pending)

    def _flush(self, pending: list[bytes]) -> None:
        small: list[bytes] = []
        for chunk in pending:
            if len(chunk) < ONE_PASS_MIN_BYTES:
                small.append(chunk)
                continue
            # writelines() joins its chunks into one new buffer (Python 3.11): a large
            # chunk goes alone, so it is copied once, by the kernel.
            self._write_all(small)
            self.transport.write(chunk)
        self._write_all(small)
        pending.clear()

    def _write_all(self, chunks: list[bytes]) -> None:
        if len(chunks) == 1:
            self.transport.write(chunks[0])
        elif chunks:
            self.transport.writelines(chunks)
        chunks.clear()
