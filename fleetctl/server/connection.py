"""A websockets server connection tuned for relaying (the thin I/O layer of the relay).

Two departures from :class:`websockets.asyncio.server.ServerConnection`, both for the
hot path:

- complete binary frames go straight from ``data_received`` to :attr:`frame_sink`
  (synchronously, no queue, no task switch). Text frames, fragmented messages, pings and
  close frames take the normal path (``recv()`` / the protocol).
- ``send_frames`` serializes a batch of frames and hands the transport one buffer,
  instead of one ``write()`` (often one syscall) per frame (from
  :class:`~fleetctl.batched_connection.BatchedWritesConnection`, shared with the client).

Flow control is unchanged: ``send_frames`` waits while the transport's write buffer is
above ``write_limit``, so a writer never queues more than that in the kernel-facing
buffer; everything else waits in the per-connection
:class:`~fleetctl.server.outbound.OutboundScheduler`, where it can be dropped.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from websockets.asyncio.server import ServerConnection
from websockets.frames import Frame, Opcode

from fleetctl.batched_connection import BatchedWritesConnection

_DATA = (Opcode.TEXT, Opcode.BINARY, Opcode.CONT)


class RelayConnection(BatchedWritesConnection, ServerConnection):
    """Server connection with a synchronous binary-frame sink and batched writes."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.frame_sink: Callable[[bytes], bool] | None = None
        self.on_lost: Callable[[], None] | None = None
        self.relay_state: Any = None
        self._fragmenting = False
        # Messages handed to the recv() path and not yet marked handled by the reader
        # (message_handled). While any is pending, binary frames queue behind them too,
        # so frames are handled in arrival order whichever path they take.
        self.pending_messages = 0

    def process_event(self, event: Any) -> None:
        """Route complete binary frames to :attr:`frame_sink`, the rest as usual.

        The sink returns ``False`` to decline a frame (e.g. before authentication); the
        frame then takes the ``recv()`` path.
        """
        sink = self.frame_sink
        if sink is not None and isinstance(event, Frame):
            opcode = event.opcode
            if (
                opcode is Opcode.BINARY
                and event.fin
                and not self._fragmenting
                and not self.pending_messages
            ):
                data = event.data
                if sink(data if isinstance(data, bytes) else bytes(data)):
                    return
            if opcode is Opcode.TEXT or opcode is Opcode.BINARY:
                self._fragmenting = not event.fin
            elif opcode is Opcode.CONT and event.fin:
                self._fragmenting = False
            if event.fin and opcode in _DATA:
                self.pending_messages += 1
        super().process_event(event)

    def message_handled(self) -> None:
        """Mark one message from ``recv()`` as handled (see :attr:`pending_messages`)."""
        self.pending_messages = max(0, self.pending_messages - 1)

    def connection_lost(self, exc: Exception | None) -> None:
        """Run :attr:`on_lost` once the TCP connection is gone."""
        super().connection_lost(exc)
        on_lost, self.on_lost = self.on_lost, None
        if on_lost is not None:
            on_lost()
