"""A websockets connection that writes a batch of frames in one transport write.

Both ends of a fleet link send many small frames (fragments, relayed telemetry).
websockets' ``send()`` costs a flow-control round through the event loop per frame and its
``send_data()`` one ``transport.write()`` (often one syscall) per chunk; :meth:`send_frames`
serializes a whole batch and :meth:`send_data` hands the transport every pending chunk at
once. Flow control is unchanged: ``send_context`` still waits while the transport's write
buffer is above ``write_limit``.

The robot client (:class:`fleetctl.client.transport.LinkConnection`) and the relay
(:class:`fleetctl.server.connection.RelayConnection`) both derive from this class.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable

from websockets.asyncio.connection import Connection


class BatchedWritesConnection(Connection):
    """Connection with batched frame sends and coalesced transport writes."""

    async def send_frames(self, frames: Iterable[bytes | str]) -> None:
        """Send each item as one frame (``str`` as text, ``bytes`` as binary), in order.

        Raises:
            ConnectionClosed: The connection is closed or closing.
        """
        async with self.send_context():
            for frame in frames:
                if isinstance(frame, str):
                    self.protocol.send_text(frame.encode())
                else:
                    self.protocol.send_binary(frame)

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
        if len(pending) == 1:
            self.transport.write(pending[0])
        elif pending:
            self.transport.writelines(pending)
        pending.clear()
