"""Another replica's no_drop frames, in the order it accepted them, whichever way they came.

No_drop frames cross replicas through the sessions' stream, stored and acknowledged, and
over core NATS too while the stream is away or a replica cannot read it (docs/scaling.md,
"In the sender's order"); a receiver delivers the first copy and drops the second by
digest. Core NATS is at-most-once: a copy lost in a dying NATS node's socket comes later
(from the stream, or with the sender's replay to a replica whose reader died), after
copies that followed it. To keep the order, each no_drop frame carries
``Fleetctl-Order: <epoch>:<seq>:<prev>``, set by its replica: a number counting its
no_drop frames (``seq``), and the number of its previous frame on the same subject
(``prev``, 0: unknown); ``epoch`` is random per replica process, so a restarted replica
starts afresh.

:class:`ReceiverOrder` keeps, per (epoch, subject), the number of the last frame it
delivered; what it holds and when it lets it go: its docstring. A frame after a gap waits
at most :data:`HOLD_S` (then the gap is skipped, counted ``order_skipped``). A frame
that comes after its successors (a skipped gap filled late) is delivered anyway, counted
``order_late``: completeness before order. Duplicates never reach this stage (the digest
check before it drops them).
"""

from __future__ import annotations

import asyncio
import logging
import secrets
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

log = logging.getLogger("fleetctl.server.cluster")

ORDER_HEADER = "Fleetctl-Order"
# How long frames after a gap wait for the missing one. It covers the slow way back: the
# receiver's reader of the stream died with a NATS node, it says so within ~1 s, and the
# sender replays its recent frames (natsfanout.READER_AWAY_HOLD_S and the reader check).
HOLD_S = 3.0
# Bounds: subjects followed (least recently used forgotten), frames held in all.
MAX_ORDER_KEYS = 16384
MAX_HELD_FRAMES = 4096
MAX_HELD_BYTES = 16 * 1024 * 1024


class SenderOrder:
    """The ``Fleetctl-Order`` values of this replica's no_drop frames."""

    def __init__(self, epoch: str | None = None) -> None:
        self.epoch = epoch or secrets.token_hex(4)
        self.seq = 0
        self._last: dict[str, int] = {}

    def stamp(self, subject: str) -> str:
        """The next frame's value, on *subject*."""
        self.seq = seq = self.seq + 1
        last = self._last
        prev = last.get(subject, 0)
        if not prev and len(last) >= MAX_ORDER_KEYS:
            last.clear()  # the next frame of each subject says "unknown" (0): no wait
        last[subject] = seq
        return f"{self.epoch}:{seq}:{prev}"


@dataclass
class _Subject:
    """One sender's frames on one subject, as received here."""

    last: int | None = None  # the last delivered; None: none yet (the stream decides)
    held: dict[int, tuple[int, bytes, float]] = field(default_factory=dict)  # prev ->
    timer: asyncio.TimerHandle | None = None


class ReceiverOrder:
    """Delivers other replicas' no_drop frames in their senders' order.

    The stream is the authority: its copies come in the sender's order, so when the
    stream copy of a frame arrives, every earlier frame this replica will ever get from
    the stream has arrived. Core NATS copies go at once when they follow the last
    delivered frame, and wait otherwise: after a gap, and the first of a subject
    (its predecessors may still come from the stream, which lags core NATS by a few
    milliseconds). A held frame goes when its predecessor comes, when the stream vouches
    for it (its own stream copy, or a later frame's), or after :data:`HOLD_S`.

    Args:
        deliver: Hands one frame to this replica's connections (it counts its own
            failures).
        counters: Where ``order_held``, ``order_skipped``, ``order_late`` and
            ``order_malformed`` are counted.
        clock: Monotonic seconds.
    """

    def __init__(self, deliver: Callable[[bytes], None], counters: dict[str, int],
                 clock: Callable[[], float] | None = None) -> None:
        self._deliver = deliver
        self.counters = counters
        for name in ("order_held", "order_skipped", "order_late", "order_malformed"):
            counters.setdefault(name, 0)
        self._clock = clock
        self._subjects: OrderedDict[tuple[str, str], _Subject] = OrderedDict()
        self._held_frames = 0
        self._held_bytes = 0

    @property
    def held(self) -> int:
        """Frames waiting for a missing predecessor now."""
        return self._held_frames

    def offer(self, order: str | None, subject: str, frame: bytes) -> None:
        """A first copy of another replica's frame on *subject* (the part after the
        subject root), from core NATS."""
        parsed = self._parse(order, frame)
        if parsed is None:
            return
        epoch, seq, prev = parsed
        state = self._state((epoch, subject))
        last = state.last
        if last is not None and seq <= last:
            self._late(frame)
        elif prev == 0 or (last is not None and prev <= last):
            state.last = seq
            self._deliver(frame)
            self._drain(state)
        else:  # after a gap, or the first: the missing one or the stream settles it
            self._hold(state, prev, seq, frame)

    def offer_stream(self, order: str | None, subject: str, frame: bytes,
                     first: bool) -> None:
        """A stream copy of another replica's frame: the first copy (*first*), or the
        second of one that came over core NATS (delivered, or held here)."""
        parsed = self._parse(order, frame if first else None)
        if parsed is None:
            return
        epoch, seq, _ = parsed
        key = (epoch, subject)
        state = self._subjects.get(key)
        if state is None:
            if not first:
                return  # its core copy was delivered and its subject forgotten since
            state = self._state(key)
        if state.held:
            self._vouch(state, seq)  # nothing before it is still coming from the stream
        if first:
            if state.last is not None and seq <= state.last:
                self._late(frame)
                return
            state.last = seq
            self._deliver(frame)
        self._drain(state)

    def forget(self, keep: Callable[[str], bool]) -> None:
        """Forget the subjects *keep* says no to (no longer followed here): when they
        are followed again, their first frame goes at once. Held frames go now."""
        for key in [k for k in self._subjects if not keep(k[1])]:
            state = self._subjects.pop(key)
            self._flush(state)

    def close(self) -> None:
        """Deliver every held frame now (the replica stops)."""
        for state in self._subjects.values():
            self._flush(state)

    # -- holding --------------------------------------------------------------------------

    def _parse(self, order: str | None, frame: bytes | None) -> tuple[str, int, int] | None:
        """``(epoch, seq, prev)``, or None: then *frame* (if any) is delivered as it is
        (latest-only, a replica that does not stamp, a malformed value)."""
        if order is not None:
            try:
                epoch, seq_text, prev_text = order.split(":")
                return epoch, int(seq_text), int(prev_text)
            except ValueError:
                self.counters["order_malformed"] += 1
        if frame is not None:
            self._deliver(frame)
        return None

    def _state(self, key: tuple[str, str]) -> _Subject:
        subjects = self._subjects
        state = subjects.get(key)
        if state is not None:
            subjects.move_to_end(key)
            return state
        state = subjects[key] = _Subject()
        if len(subjects) > MAX_ORDER_KEYS:
            self._flush(subjects.popitem(last=False)[1])
        return state

    def _late(self, frame: bytes) -> None:
        self.counters["order_late"] += 1  # its successors went on without it
        self._deliver(frame)

    def _now(self) -> float:
        return self._clock() if self._clock is not None else asyncio.get_running_loop().time()

    def _hold(self, state: _Subject, prev: int, seq: int, frame: bytes) -> None:
        if prev in state.held:  # two frames claim the same predecessor: not a chain
            self.counters["order_malformed"] += 1
            self._deliver(frame)
            return
        self.counters["order_held"] += 1
        state.held[prev] = (seq, frame, self._now())
        self._held_frames += 1
        self._held_bytes += len(frame)
        if self._held_frames > MAX_HELD_FRAMES or self._held_bytes > MAX_HELD_BYTES:
            self._skip(state)  # over the bounds: this subject's gap is not waited for
        elif state.timer is None:
            self._arm(state)

    def _vouch(self, state: _Subject, seq: int) -> None:
        """The stream brought frame *seq*: held frames up to it go, in order."""
        for prev in sorted((p for p, v in state.held.items() if v[0] <= seq),
                           key=lambda p: state.held[p][0]):
            seq_held, frame, _ = self._pop(state, prev)
            if state.last is None or seq_held > state.last:
                state.last = seq_held
            self._deliver(frame)

    def _pop(self, state: _Subject, prev: int) -> tuple[int, bytes, float]:
        entry = state.held.pop(prev)
        self._held_frames -= 1
        self._held_bytes -= len(entry[1])
        if not state.held and state.timer is not None:
            state.timer.cancel()
            state.timer = None
        return entry

    def _arm(self, state: _Subject) -> None:
        if not state.held:
            return
        oldest = min(at for _, _, at in state.held.values())
        delay = max(0.0, oldest + HOLD_S - self._now())
        state.timer = asyncio.get_running_loop().call_later(delay, self._expire, state)

    def _expire(self, state: _Subject) -> None:
        state.timer = None
        now = self._now()
        while state.held and min(at for _, _, at in state.held.values()) + HOLD_S <= now:
            self._skip(state)
        if state.held and state.timer is None:
            self._arm(state)

    def _skip(self, state: _Subject, *, quiet: bool = False) -> None:
        """Give up on the oldest gap: deliver the first held frame after it, and what
        follows it."""
        prev = min(state.held, key=lambda p: state.held[p][0])
        state.last = prev  # as if the missing frame had come
        skipped = self.counters["order_skipped"] = self.counters["order_skipped"] + 1
        if not quiet and skipped % 100 == 1:  # the first, then every 100th
            log.warning("no_drop frames from another replica: a frame did not come within "
                        "%g s (core NATS and the stream both lost it, or it is late): the "
                        "ones after it go on (%d such gaps so far)", HOLD_S, skipped)
        self._drain(state)

    def _drain(self, state: _Subject) -> None:
        held = state.held
        while held and state.last is not None and state.last in held:
            seq, frame, _ = self._pop(state, state.last)
            state.last = seq
            self._deliver(frame)

    def _flush(self, state: _Subject) -> None:
        while state.held:
            self._skip(state, quiet=True)
        if state.timer is not None:
            state.timer.cancel()
            state.timer = None


def order_subject(subject: str) -> str:
    """The part of a live or stream subject after its root: the same for both copies."""
    return subject.partition(".")[2]


def covered_by(wanted: Iterable[str]) -> Callable[[str], bool]:
    """Whether a subject (after its root) is still followed, given the live subjects
    *wanted* (``fleetctl.husky1.>``...). A set lookup per prefix of the subject, not a
    match per wanted subject: it runs for every remembered subject on every change."""
    from fleetctl.server.cluster.subjects import covered, subject_matches

    tails = {order_subject(w) for w in wanted}
    if ">" in tails:
        return lambda tail: True
    wild = {t[:-2] for t in tails if t.endswith(".>")}
    exact = {t for t in tails if "*" not in t and not t.endswith(".>")}
    other = ["x." + t for t in tails if "*" in t]  # not made by interest today; kept exact
    return lambda tail: (tail in exact or covered(tail, wild)
                         or any(subject_matches("x." + tail, o) for o in other))
