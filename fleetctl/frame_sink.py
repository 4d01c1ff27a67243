"""Complete binary frames handed over in the read that brought them (both ends of a link).

websockets' asyncio connection puts every received message in a queue; a task awaiting
``recv()`` (or ``async for``) takes it in the event loop's next round. For a relay or a
receiver of telemetry that round is most of the cost of a small message: on loopback it
put 0.08-0.2 ms on each delivery (docs/benchmarks.md). A :class:`FrameSink` connection
gives each complete, unfragmented binary frame to :attr:`FrameSink.frame_sink` from
``data_received`` instead, synchronously. Text frames, fragmented messages, pings and the
close frame take websockets' normal path.

Order is kept: while a message handed to the ``recv()`` path has not been marked handled
(:meth:`FrameSink.message_handled`), binary frames queue behind it on that path too, so a
reader sees every data frame in the order it arrived whichever way it went.

Used by the relay (:class:`fleetctl.server.connection.RelayConnection`), the robot
client's link (:class:`fleetctl.client.transport.LinkConnection`) and the e2e consumer.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from websockets.frames import Frame, Opcode

_DATA = (Opcode.TEXT, Opcode.BINARY, Opcode.CONT)


class FrameSink:
    """Mixin for a websockets asyncio connection (put it first among the bases).

    Attributes:
        frame_sink: Takes a complete binary frame's payload; returns ``False`` to decline
            it (it then takes the ``recv()`` path). None: every frame takes that path.
        pending_messages: Messages handed to the ``recv()`` path and not yet marked
            handled.
        max_message_frames: Frames one fragmented message may have while
            :attr:`frame_sink` is set (``None``: any number); the continuation frame past
            it is dropped and :meth:`too_many_frames` called. Why: websockets bounds a
            message's bytes, not its frames, and keeps every frame until the last one
            (empty continuation frames cost ~100 bytes each and nothing against
            ``max_size``). Counted off the fast path: complete frames never reach it.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.frame_sink: Callable[[bytes], bool] | None = None
        self.pending_messages = 0
        self.max_message_frames: int | None = None
        self._fragmenting = False
        self._message_frames = 0  # frames of the fragmented message being received

    def process_event(self, event: Any) -> None:
        """Route complete binary frames to :attr:`frame_sink`, the rest as usual."""
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
                self._message_frames = 1
            elif opcode is Opcode.CONT:
                self._message_frames += 1
                limit = self.max_message_frames
                if limit is not None and self._message_frames > limit:
                    self.too_many_frames()
                    return  # not assembled: the message is refused whole
                if event.fin:
                    self._fragmenting = False
            if event.fin and opcode in _DATA:
                self.pending_messages += 1
        super().process_event(event)  # type: ignore[misc]  # the connection's own

    def too_many_frames(self) -> None:
        """A fragmented message passed :attr:`max_message_frames` (called for each frame
        past it); subclasses close the connection."""

    def message_handled(self) -> None:
        """Mark one message from ``recv()`` as handled (see :attr:`pending_messages`)."""
        self.pending_messages = max(0, self.pending_messages - 1)
