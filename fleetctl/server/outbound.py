"""Per-connection outbound scheduler (MISSION "Server"; Robofleet Algorithm 2 applied to
the server side). Pure data structure, no I/O: the connection's writer task pops from it
only as fast as the socket drains.

Four queues, served in this order:

1. control text frames (welcome, errors): a small FIFO;
2. latched frames (:mod:`fleetctl.server.latched`): the stored latched messages a new
   subscription gets, a FIFO of whole messages on the no_drop side (never superseded).
   It has its own byte bound (``max_latched_bytes``): a message that does not fit whole
   is dropped whole and counted (a partial fragmented message would be useless), except
   that an empty latched queue always takes one message. Its frames are the store's own
   ``bytes`` objects, so queueing them costs references, not copies; they are outside
   the byte bound of the other queues (``queued_bytes``), like a session backlog;
3. no_drop frames: a FIFO bounded in messages and bytes; overflow drops the *new* frame
   (keeps order of what is already queued) and counts it;
4. droppable topics: one slot per topic holding only the latest message. A newer message
   replaces a pending one (the old one is counted as dropped). Fragments
   (``fleetctl_msgs/msg/Fragment``) of the latest message are kept together; a superseded
   partial message is dropped whole. Topics are served round-robin one frame at a time,
   so fragments of a big message interleave with small messages of other topics.

The byte bound covers queues 1, 3 and 4; a frame that does not fit is dropped and
counted, except that an empty queue always takes one frame (else a frame larger than the
bound could never be delivered; memory stays below bound + one max frame).

Named sessions (:mod:`fleetctl.server.sessions`) add two things, both off unless used:

- a *backlog*: a session's mailbox, queued at the head of the no_drop FIFO when a
  connection attaches (:meth:`OutboundScheduler.push_backlog`). It was already bounded
  by the mailbox limits, so it is outside the FIFO's message and byte bounds (nothing is
  dropped when it moves in); live no_drop frames queue behind it under the usual bounds.
- acknowledgement tracking (:meth:`OutboundScheduler.track_acks`): no_drop frames handed
  to the writer are kept until a pong acknowledges them (:meth:`acked`), so that a
  connection that dies gives back what it may not have delivered (:meth:`take_no_drop`).
  Latched frames are not given back: a resumed session subscribes again, which queues
  the store's latched messages again.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable

CONTROL_TOPIC = "<control>"
# Why 256: control frames answer the client's own requests; a client that floods
# requests and never reads loses answers rather than growing our memory.
MAX_CONTROL_FRAMES = 256

Frame = bytes | str


class _Slot:
    __slots__ = ("broken_id", "frames", "message_id", "nbytes")

    def __init__(self) -> None:
        self.frames: deque[bytes] = deque()
        self.message_id: int | None = None
        self.broken_id: int | None = None
        self.nbytes = 0


class OutboundScheduler:
    """Bounded queues of one connection.

    Args:
        max_bytes: Bytes that may be queued across all queues.
        max_no_drop_messages: Frames the no_drop FIFO may hold.
        wake: Called when the scheduler goes from empty to non-empty (the writer's cue).
        on_drop: Called with ``(topic, frames)`` for every drop (server-wide metrics).
        max_latched_bytes: Bytes the latched queue may hold; ``None`` means *max_bytes*.
    """

    def __init__(
        self,
        max_bytes: int,
        max_no_drop_messages: int,
        wake: Callable[[], None] | None = None,
        on_drop: Callable[[str, int], None] | None = None,
        max_latched_bytes: int | None = None,
    ) -> None:
        self.max_bytes = max_bytes
        self.max_no_drop_messages = max_no_drop_messages
        self.max_latched_bytes = max_bytes if max_latched_bytes is None else max_latched_bytes
        self._latched: deque[tuple[str, bytes]] = deque()
        self.latched_bytes = 0
        self._wake = wake
        self._on_drop = on_drop
        self._control: deque[str] = deque()
        self._no_drop: deque[tuple[str, bytes]] = deque()
        self._slots: dict[str, _Slot] = {}
        self._ready: deque[str] = deque()
        self.queued_bytes = 0
        self.queued_frames = 0
        self.drops: dict[str, int] = {}
        self.dropped_total = 0
        self._backlog_left = 0  # the first _backlog_left frames of _no_drop are backlog
        self.backlog_bytes = 0
        self._unacked: deque[tuple[str, bytes]] | None = None
        self._popped = 0  # no_drop frames popped while tracking (ack marks count these)
        self._retired = 0  # ... of which acknowledged
        self._marked = 0  # mark of the last ping

    def __len__(self) -> int:
        return self.queued_frames

    def _count_drop(self, topic: str, n: int = 1) -> None:
        self.drops[topic] = self.drops.get(topic, 0) + n
        self.dropped_total += n
        if self._on_drop is not None:
            self._on_drop(topic, n)

    def _fits(self, size: int) -> bool:
        return self.queued_frames == 0 or self.queued_bytes + size <= self.max_bytes

    def _added(self, size: int) -> None:
        was_empty = self.queued_frames == 0
        self.queued_bytes += size
        self.queued_frames += 1
        if was_empty and self._wake is not None:
            self._wake()

    def push_control(self, text: str) -> bool:
        """Queue a control text frame; return ``False`` (counted) if the FIFO is full."""
        if len(self._control) >= MAX_CONTROL_FRAMES:
            self._count_drop(CONTROL_TOPIC)
            return False
        self._control.append(text)
        self._added(len(text))
        return True

    def push_latched(self, topic: str, frames: list[bytes]) -> bool:
        """Queue the frames of one stored latched message (a whole frame, or all the
        fragments of one message in index order), ahead of no_drop and droppable frames.

        Returns:
            Whether the message was queued; when it does not fit the latched queue's
            bound it is dropped whole and each frame counted in :attr:`drops`.
        """
        size = sum(len(f) for f in frames)
        if self._latched and self.latched_bytes + size > self.max_latched_bytes:
            self._count_drop(topic, len(frames))
            return False
        was_empty = self.queued_frames == 0
        self._latched.extend((topic, f) for f in frames)
        self.latched_bytes += size
        self.queued_frames += len(frames)
        if frames and was_empty and self._wake is not None:
            self._wake()
        return True

    @property
    def latched_frames(self) -> int:
        """Frames of stored latched messages still queued here."""
        return len(self._latched)

    def push(self, topic: str, frame: bytes, no_drop: bool, message_id: int | None = None) -> bool:
        """Queue one frame for this connection.

        Args:
            topic: The frame's topic (a fragment's original topic).
            frame: The encoded frame, sent as is.
            no_drop: Deliver reliably and in order (FIFO) instead of latest-only.
            message_id: For a fragment, its ``message_id``; ``None`` for a whole message.

        Returns:
            Whether the frame was queued; a ``False`` is counted in :attr:`drops`.
        """
        size = len(frame)
        if no_drop:
            if (len(self._no_drop) - self._backlog_left >= self.max_no_drop_messages
                    or not self._fits(size)):
                self._count_drop(topic)
                return False
            self._no_drop.append((topic, frame))
            self._added(size)
            return True
        return self._push_latest(topic, frame, size, message_id)

    def _push_latest(self, topic: str, frame: bytes, size: int, message_id: int | None) -> bool:
        slot = self._slots.get(topic)
        if slot is None:
            slot = self._slots[topic] = _Slot()
            self._ready.append(topic)
        if message_id is not None and message_id == slot.broken_id:
            self._count_drop(topic)  # the rest of a message we already gave up on
            return False
        continuing = message_id is not None and message_id == slot.message_id
        if slot.frames and not continuing:
            self._discard(slot)
            self._count_drop(topic)  # the superseded message, whole
        if not self._fits(size):
            if slot.frames:  # the partial message cannot complete: drop it whole
                self._discard(slot)
            slot.broken_id = message_id
            self._count_drop(topic)
            return False
        slot.message_id = message_id
        slot.frames.append(frame)
        slot.nbytes += size
        self._added(size)
        return True

    def _discard(self, slot: _Slot) -> None:
        self.queued_bytes -= slot.nbytes
        self.queued_frames -= len(slot.frames)
        slot.frames.clear()
        slot.nbytes = 0

    def pop(self) -> tuple[str, Frame] | None:
        """Return ``(topic, frame)`` to send next, or ``None`` when nothing is queued.

        Control frames come with topic :data:`CONTROL_TOPIC`.
        """
        if self._control:
            text = self._control.popleft()
            self.queued_bytes -= len(text)
            self.queued_frames -= 1
            return CONTROL_TOPIC, text
        if self._latched:
            latched = self._latched.popleft()
            self.latched_bytes -= len(latched[1])
            self.queued_frames -= 1
            return latched
        if self._no_drop:
            item = self._no_drop.popleft()
            if self._backlog_left:
                self._backlog_left -= 1
                self.backlog_bytes -= len(item[1])
            else:
                self.queued_bytes -= len(item[1])
            self.queued_frames -= 1
            if self._unacked is not None:
                self._unacked.append(item)
                self._popped += 1
            return item
        return self._pop_latest()

    def _pop_latest(self) -> tuple[str, bytes] | None:
        while self._ready:
            topic = self._ready.popleft()
            slot = self._slots[topic]
            if not slot.frames:
                del self._slots[topic]
                continue
            frame = slot.frames.popleft()
            size = len(frame)
            slot.nbytes -= size
            self.queued_bytes -= size
            self.queued_frames -= 1
            if slot.frames:
                self._ready.append(topic)  # interleave: one fragment, then the next topic
            elif slot.message_id is None:
                del self._slots[topic]
            else:
                # Keep the slot (empty) out of the ready line only until its next fragment;
                # it must remember message_id so later fragments continue the message.
                self._ready.append(topic)
            return topic, frame
        return None

    # -- named sessions ---------------------------------------------------------------------

    @property
    def backlog_frames(self) -> int:
        """Frames of a session's mailbox still queued here."""
        return self._backlog_left

    def push_backlog(self, frames: Iterable[tuple[str, bytes]]) -> None:
        """Queue ``(topic, frame)`` no_drop frames (a session's mailbox) before any later
        no_drop frame, outside the FIFO's bounds (the mailbox had its own).

        Call before any live no_drop frame is queued: the relay does it when the
        connection attaches to its session, before reinstating its subscriptions.
        """
        was_empty = self.queued_frames == 0
        n = 0
        for topic, frame in frames:
            self._no_drop.append((topic, frame))
            self.backlog_bytes += len(frame)
            n += 1
        self._backlog_left += n
        self.queued_frames += n
        if n and was_empty and self._wake is not None:
            self._wake()

    def track_acks(self) -> None:
        """From now on keep popped no_drop frames until :meth:`acked` (see module doc)."""
        if self._unacked is None:
            self._unacked = deque()

    def ack_mark(self) -> int | None:
        """A mark for a ping sent after the frames popped so far, or ``None`` when no
        tracked frame was popped since the previous mark (no ping needed)."""
        if self._unacked is None or self._popped == self._marked:
            return None
        self._marked = self._popped
        return self._popped

    def acked(self, mark: int) -> None:
        """The pong of the ping of *mark* came back: forget the frames popped before it."""
        unacked = self._unacked
        if unacked is None:
            return
        while self._retired < mark and unacked:
            unacked.popleft()
            self._retired += 1

    @property
    def acked_total(self) -> int:
        """no_drop frames acknowledged since tracking began (a session's stream cursor
        follows this count)."""
        return self._retired

    @property
    def no_drop_queued(self) -> int:
        """Live no_drop frames queued (the FIFO's bound counts these)."""
        return len(self._no_drop) - self._backlog_left

    @property
    def unacked_frames(self) -> int:
        """no_drop frames popped but not yet acknowledged (0 when not tracking)."""
        return len(self._unacked) if self._unacked is not None else 0

    def take_no_drop(self) -> list[tuple[str, bytes]]:
        """Remove and return, in order, the unacknowledged popped no_drop frames and every
        queued one (backlog included); stop tracking. For a connection that is gone."""
        out = list(self._unacked or ())
        out.extend(self._no_drop)
        queued = sum(len(f) for _, f in self._no_drop) - self.backlog_bytes
        self.queued_bytes -= queued
        self.queued_frames -= len(self._no_drop)
        self._no_drop.clear()
        self._backlog_left = self.backlog_bytes = 0
        self._unacked = None
        self._popped = self._retired = self._marked = 0
        return out

    def pop_batch(self, max_bytes: int) -> list[tuple[str, Frame]]:
        """Pop frames until about *max_bytes* are taken (at least one if any is queued)."""
        out: list[tuple[str, Frame]] = []
        taken = 0
        while taken < max_bytes:
            item = self.pop()
            if item is None:
                break
            out.append(item)
            taken += len(item[1])
        return out
