"""A relay connection's pongs, held until the no_drop frames before their ping are stored.

In a cluster, a robot's pong means "stored in the sessions' stream", not only "read by
this process" (why: :mod:`fleetctl.server.cluster.storeacks`). websockets answers a ping
inside its protocol object (``Protocol.recv_frame`` calls ``send_frame`` with the pong);
:class:`HeldPongs` takes the connection's ``send_frame`` and queues a pong whose frames
are not stored yet, then sends it, in order, when they are. Other frames pass untouched.

Bounded: a pong waits at most :data:`PONG_HOLD_MAX_S` (why: the constant's comment), and
at most :data:`MAX_HELD_PONGS` wait per connection. Past that the oldest is
dropped (counted ``coalesced``): a pong acknowledges its ping and every earlier one
(websockets' clients, and so the robot's link, read it so), so the later pong still
acknowledges it. A ping carries at most 125 bytes.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from websockets.frames import Frame, Opcode
from websockets.protocol import State

from fleetctl.server.cluster.storeacks import StoreAcks

MAX_HELD_PONGS = 64
# A pong waits at most this long. Why a bound: the robot's send window opens on pongs, so a
# store that hangs (a NATS node that died holding the stream's leader: JetStream takes
# 1-3 s to elect another, and a store times out after 1 s) would stall all its traffic,
# droppable too. A working store takes 1-4 ms (docs/scaling.md); past the bound the pong
# goes (counted ``pongs_unstored``) and the frames are at risk only if this replica dies
# before JetStream comes back: a second fault.
PONG_HOLD_MAX_S = 0.25


class HeldPongs:
    """Hold *connection*'s pongs until :meth:`StoreAcks.stored` is true for their mark,
    or :data:`PONG_HOLD_MAX_S` passed.

    websockets answers a ping while it parses what was read, before the frames read with
    it are handled: a pong is therefore only queued by :meth:`send_frame`, and its mark
    taken by :meth:`settle`, which the connection calls once everything read before the
    ping was handled.

    Args:
        connection: A websockets connection (its ``protocol`` and ``send_data``).
        acks: The replica's store counters.
        mark: The number of the last no_drop frame the connection sent.
        hold_max_s: The bound of a pong's wait.
    """

    def __init__(self, connection: Any, acks: StoreAcks, mark: Callable[[], int],
                 hold_max_s: float = PONG_HOLD_MAX_S) -> None:
        self._connection = connection
        self._acks = acks
        self._mark = mark
        self._hold_max_s = hold_max_s
        # [mark (None until settled), queued at, pong], oldest first
        self._held: deque[list[Any]] = deque()
        self._registered = False  # a callback is waiting in acks
        self._timer: asyncio.TimerHandle | None = None
        protocol = connection.protocol
        self._send_frame: Callable[[Frame], None] = protocol.send_frame
        protocol.send_frame = self.send_frame  # the instance's, which recv_frame calls

    @property
    def waiting(self) -> int:
        """Pongs held now."""
        return len(self._held)

    def send_frame(self, frame: Frame) -> None:
        """websockets' ``send_frame``: pongs are queued until :meth:`settle`."""
        if frame.opcode is not Opcode.PONG:
            self._send_frame(frame)
            return
        held = self._held
        if len(held) >= MAX_HELD_PONGS:
            held.popleft()
            self._acks.coalesced += 1
        held.append([None, time.monotonic(), frame])

    def settle(self) -> None:
        """The frames read before the queued pongs' pings are handled: give those pongs
        the connection's mark now, send what may go, wait for the rest."""
        held = self._held
        if not held or held[-1][0] is not None:
            return
        mark, settled = self._mark(), 0
        for entry in reversed(held):
            if entry[0] is not None:
                break
            entry[0] = mark
            settled += 1
        acks = self._acks
        self._send_while(lambda mark, _at: acks.stored(mark))
        acks.held += min(settled, len(held))  # those of them that wait

    def _wait(self) -> None:
        """Be called back when the oldest held pong's frames are stored, or it is due."""
        held = self._held
        if not held:
            return
        if not self._registered and held[0][0] is not None:
            self._registered = True
            self._acks.wait(held[0][0], self._release)  # may call it back at once
        if held and self._timer is None:
            loop = asyncio.get_running_loop()
            due = held[0][1] + self._hold_max_s
            self._timer = loop.call_at(loop.time() + max(0.0, due - time.monotonic()),
                                       self._expire)

    def _release(self) -> None:
        """Send the held pongs whose frames are stored, in order; wait for the next."""
        self._registered = False
        acks = self._acks
        self._send_while(lambda mark, _at: mark is not None and acks.stored(mark))

    def _expire(self) -> None:
        """Send the held pongs that waited :data:`PONG_HOLD_MAX_S`, stored or not."""
        self._timer = None
        now, acks = time.monotonic(), self._acks

        def due(mark: int | None, at: float) -> bool:
            if mark is None:  # its frames are not handled yet (held over a rate): never
                return False
            if acks.stored(mark):
                return True
            if now - at >= self._hold_max_s:
                acks.unstored += 1
                return True
            return False

        self._send_while(due)

    def _send_while(self, ready: Callable[[Any, float], bool]) -> None:
        held = self._held
        if self._connection.protocol.state is not State.OPEN:
            held.clear()  # closing: nobody reads pongs any more
            self._cancel_timer()
            return
        head = held[0] if held else None
        sent = False
        while held and ready(held[0][0], held[0][1]):
            self._send_frame(held.popleft()[2])
            sent = True
        if sent:
            with contextlib.suppress(OSError, RuntimeError):  # a transport closing meanwhile
                self._connection.send_data()
        if (held[0] if held else None) is not head:
            self._cancel_timer()  # it was armed for the old head
        self._wait()

    def _cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
