"""Stores in the sessions' stream that wait for JetStream's acknowledgement, oldest first.

A replica stores each no_drop frame of its local senders in the stream
(:mod:`~fleetctl.server.cluster.sharedsessions`). nats-py's ``JetStreamContext.publish``
is one request per frame: a reply inbox, a future and an ``asyncio.wait_for`` timer each,
~37 us of CPU per frame here against ~13 us for a plain publish with a reply subject and
one subscription for every acknowledgement (measured side by side, 20,000 frames). And
awaited in batches (64 out, then all 64 acknowledged), a frame that came while a batch
was out waited for that batch before it was even published: ~0.7 ms of the 1.5 ms the
stream added to a cross-replica hop at 5,000 no_drop frames/s.

:class:`StreamStores` publishes each frame with the reply subject ``<inbox>.<n>`` and
takes the acknowledgements on one subscription (``<inbox>.*``); up to *window* frames are
out at once, and the owner retires them in the order they were sent (so the store queue,
and the count of stored frames the held pongs wait on, advance in order). An
acknowledgement that does not come within *timeout_s* (a request lost in a dead NATS
node's socket) is a :class:`TimeoutError`, as ``publish`` raised it; after a failure the
owner forgets what is out (:meth:`forget`) and sends it all again, and late
acknowledgements of forgotten frames are ignored (JetStream drops the second copy of a
frame it stored, by ``Nats-Msg-Id``).

Measured against the batches (``benchmarks/cluster_throughput.py``, alternating, 2 cores,
2026-11-28): a replica stores every no_drop frame up to 15,000-20,000 frames/s against
10,000 (past that, 18,000-21,000/s against 11,000-13,000/s, the rest counted
``queue_full``); the cross-replica hop at 5,000 frames/s p50 1.7-2.1 ms against 2.0-2.8,
p99 3.7-5.7 against 4.5-9.3; the same-replica hop of those no_drop frames p50 0.72-0.91
ms against 0.51-0.65 (the stores now go out between the frames, on the same two cores).
"""

from __future__ import annotations

import contextlib
import json
import time
from collections import deque
from collections.abc import Callable

from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.aio.subscription import Subscription
from nats.errors import Error as NatsError
from nats.js import api
from nats.js.errors import APIError, NoStreamResponseError

# A no-responders status on a reply: no stream leader took the publish.
_NO_RESPONDERS = "503"
_PENDING = object()


class StreamStores:
    """Frames published to the stream and not yet retired by the owner, oldest first.

    Args:
        stream: The stream's name (``Nats-Expected-Stream``: JetStream refuses a frame
            that would land in another stream).
        window: Frames out at once, at most.
        timeout_s: An acknowledgement later than this is a :class:`TimeoutError`.
        on_ack: Called on every acknowledgement of a frame still out (the owner's wake).
        counters: ``stored`` and ``duplicates`` are counted here.
        clock: Monotonic seconds.
    """

    def __init__(self, stream: str, window: int, timeout_s: float, on_ack: Callable[[], None],
                 counters: dict[str, int],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.stream = stream
        self.window = window
        self.timeout_s = timeout_s
        self._on_ack = on_ack
        self._counters = counters
        self._clock = clock
        self._prefix = ""
        self._sub: Subscription | None = None
        self._next = 0  # the next frame's number
        self._out: deque[tuple[int, float]] = deque()  # (number, sent at), oldest first
        self._results: dict[int, object] = {}  # number -> None (stored) or the error

    async def start(self, nc: Client) -> None:
        """Subscribe to the acknowledgements (once per connection object: nats-py
        restores the subscription after a reconnect)."""
        self._prefix = nc.new_inbox()
        self._sub = await nc.subscribe(self._prefix + ".*", cb=self._acknowledged)

    async def stop(self) -> None:
        if self._sub is not None:
            with contextlib.suppress(NatsError):  # the connection is gone already
                await self._sub.unsubscribe()
            self._sub = None

    def __len__(self) -> int:
        return len(self._out)

    def has_room(self) -> bool:
        return len(self._out) < self.window

    async def send(self, nc: Client, subject: str, frame: bytes,
                   headers: dict[str, str]) -> None:
        """Publish one frame to the stream; its outcome comes from :meth:`oldest`.

        A publish nats-py refuses at once (too big, connection closed) is that frame's
        outcome; nothing is raised."""
        number = self._next
        self._next += 1
        self._out.append((number, self._clock()))
        headers[api.Header.EXPECTED_STREAM] = self.stream
        try:
            await nc.publish(subject, frame, reply=f"{self._prefix}.{number}",
                             headers=headers)
        except NatsError as exc:
            self._results[number] = exc

    def skip(self) -> None:
        """One frame that is not published at all, finished at once (counted by the
        caller): it keeps its place in the order."""
        number = self._next
        self._next += 1
        self._out.append((number, self._clock()))
        self._results[number] = None

    def oldest(self) -> tuple[bool, BaseException | None]:
        """The oldest frame's outcome once it has one: ``(True, None)`` stored,
        ``(True, error)`` failed (:class:`TimeoutError` past *timeout_s*); ``(False,
        None)`` while it waits (or nothing is out). A frame with an outcome leaves."""
        if not self._out:
            return False, None
        number, sent_s = self._out[0]
        result = self._results.pop(number, _PENDING)
        if result is _PENDING:
            if self._clock() - sent_s < self.timeout_s:
                return False, None
            result = TimeoutError(f"no acknowledgement from the stream in {self.timeout_s} s")
        self._out.popleft()
        assert result is None or isinstance(result, BaseException)
        return True, result

    def wait_s(self) -> float | None:
        """Seconds until the oldest frame out times out (None: nothing is out)."""
        if not self._out:
            return None
        return max(0.0, self._out[0][1] + self.timeout_s - self._clock())

    def forget(self) -> None:
        """Forget every frame out (they are sent again); their late acknowledgements
        are ignored."""
        self._out.clear()
        self._results.clear()

    async def _acknowledged(self, msg: Msg) -> None:
        try:
            number = int(msg.subject.rpartition(".")[2])
        except ValueError:
            return
        if not self._out or not self._out[0][0] <= number < self._next:
            return  # forgotten (sent again since), or not ours
        self._results[number] = self._outcome(msg)
        self._on_ack()

    def _outcome(self, msg: Msg) -> BaseException | None:
        if msg.headers and msg.headers.get(api.Header.STATUS) == _NO_RESPONDERS:
            return NoStreamResponseError()
        try:
            answer = json.loads(msg.data)
        except ValueError as exc:
            return APIError(description=f"unreadable acknowledgement: {exc}")
        if not isinstance(answer, dict):
            return APIError(description="unreadable acknowledgement")
        if "error" in answer:
            try:
                APIError.from_error(answer["error"])  # raises the error's own class
            except APIError as exc:
                return exc
            except (TypeError, ValueError, KeyError):  # not an error as JetStream words it
                pass
            return APIError(description=f"unreadable error: {answer['error']!r:.200}")
        self._counters["duplicates" if answer.get("duplicate") else "stored"] += 1
        return None
