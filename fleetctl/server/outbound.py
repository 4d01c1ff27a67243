"""Per-connection outbound scheduler (MISSION "Server"; Robofleet Algorithm 2 applied to
the server side). Pure data structure, no I/O: the connection's writer task pops from it
only as fast as the socket drains.

Three queues, served in this order:

1. control text frames (welcome, errors): a small FIFO;
2. no_drop frames: a FIFO bounded in messages and bytes; overflow drops the *new* frame
   (keeps order of what is already queued) and counts it;
3. droppable topics: one slot per topic holding only the latest message. A newer message
   replaces a pending one (the old one is counted as dropped). Fragments
   (``fleetctl_msgs/msg/Fragment``) of the latest message are kept together; a superseded
   partial message is dropped whole. Topics are served round-robin one frame at a time,
   so fragments of a big message interleave with small messages of other topics.

The byte bound covers everything queued; a frame that does not fit is dropped and
counted, except that an empty queue always takes one frame (else a frame larger than the
bound could never be delivered; memory stays below bound + one max frame).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

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
    """

    def __init__(
        self,
        max_bytes: int,
        max_no_drop_messages: int,
        wake: Callable[[], None] | None = None,
        on_drop: Callable[[str, int], None] | None = None,
    ) -> None:
        self.max_bytes = max_bytes
        self.max_no_drop_messages = max_no_drop_messages
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
            if len(self._no_drop) >= self.max_no_drop_messages or not self._fits(size):
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
        if self._no_drop:
            item = self._no_drop.popleft()
            self.queued_bytes -= len(item[1])
            self.queued_frames -= 1
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
