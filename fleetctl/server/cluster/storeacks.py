"""How far the sessions' stream has stored the no_drop frames local senders sent.

Why: a robot counts its no_drop frames delivered once the pong of a later ping comes
back (``fleetctl.client.transport``: after a reconnect it resends what is not
acknowledged, and forgets the rest). In a cluster a replica also stores each of those
frames in the sessions' JetStream stream, the only copy sessions and other replicas read.
A replica killed after answering the ping but before JetStream acknowledged the store
lost the frame for them, though the robot had been told it was delivered. So a ping's
pong waits until every no_drop frame its connection sent before it is stored
(:class:`~fleetctl.server.heldpongs.HeldPongs`): what was not stored is not
acknowledged, and the robot resends it through the next replica (stored once: the
stream drops a duplicate by ``Nats-Msg-Id``).

Frames are stored in the order they were offered (one FIFO, popped in order), so a
counter of frames offered and one of frames done (stored, a duplicate, refused) say which
are stored: frame number *n* is when ``done >= n``. While the stream is away (NATS lost,
stores failing) nothing waits: the frames go to local receivers and other replicas
live, as without a stream, and the window is back until storing works again.
"""

from __future__ import annotations

import heapq
import itertools
import logging
from collections.abc import Callable

log = logging.getLogger("fleetctl.server.cluster")


class StoreAcks:
    """Frame counters of the sessions' store queue, and callbacks waiting on them.

    Attributes:
        offered: No_drop frames queued for the stream so far (the last one's number).
        done: Frames the store loop finished with, in queue order.
        bypass: The stream is away: every mark counts as stored.
        held: Pongs that had to wait (counted by :class:`~fleetctl.server.heldpongs.
            HeldPongs`).
        coalesced: Held pongs dropped because a later one acknowledges their ping too.
        unstored: Held pongs sent before their frames were stored (the hold's bound).
    """

    def __init__(self) -> None:
        self.offered = 0
        self.done = 0
        self.bypass = False
        self.held = 0
        self.coalesced = 0
        self.unstored = 0
        self._waiters: list[tuple[int, int, Callable[[], None]]] = []
        self._order = itertools.count()  # ties: first come, first called

    def stored(self, mark: int) -> bool:
        """Whether every frame up to number *mark* is stored (or the stream is away)."""
        return self.bypass or mark <= self.done

    def wait(self, mark: int, callback: Callable[[], None]) -> None:
        """Call *callback* once :meth:`stored` is true for *mark* (at once if it is)."""
        if self.stored(mark):
            callback()
            return
        heapq.heappush(self._waiters, (mark, next(self._order), callback))

    def note_offered(self) -> int:
        """One more frame queued for the stream; its number."""
        self.offered += 1
        return self.offered

    def note_done(self) -> None:
        """The oldest frame in the store queue is finished with."""
        self.done += 1
        if self._waiters and self._waiters[0][0] <= self.done:
            self._release()

    def set_bypass(self, away: bool) -> None:
        """The stream went away (*away*) or came back."""
        self.bypass = away
        if away:
            self._release()

    def release_all(self) -> None:
        """Call every waiting callback now (the replica stops)."""
        self.bypass = True
        self._release()

    def _release(self) -> None:
        waiters = self._waiters
        while waiters and self.stored(waiters[0][0]):
            callback = heapq.heappop(waiters)[2]
            try:
                callback()
            except Exception:  # one connection's failure must not hold the others' pongs
                log.exception("releasing a held pong failed")
