"""An ordered set of stored topics that lists the few a pattern may match.

A new subscription gets the stored latched messages and a keyframe request for the video
topics it starts receiving (:mod:`fleetctl.server.firstframes`); the latched store and the
keyframe router each hold up to 4,096 topics. Matching the pattern against every one cost
the event loop 14.7 ms a subscribe with a full latched store (google-re2: 6-10 us a call
here, docs/security.md). :class:`TopicIndex` keeps the topics sorted by their UTF-8 bytes
as well, so a pattern whose matches RE2 can bound (:meth:`FullMatch.bounds`: ``/robot7/.*``
lies between ``/robot7/`` and ``/robot7/\\xf4...``) is matched only against the topics in
that range, found by bisection; a literal topic is one lookup. Patterns RE2 cannot bound
(``.*``, ``.*scan``) still get every topic: the relay charges their work to the
connection's control request rate instead
(:data:`~fleetctl.server.firstframes.WORK_PER_CONTROL_REQUEST`).

The set keeps an order of its own (insertion order; adding a topic again moves it last),
the order the stores used to list their topics in, so candidates come in that order.
"""

from __future__ import annotations

import bisect
import itertools
from collections.abc import Iterator, Sequence

from fleetctl.server.regex import FullMatch


def topic_key(topic: str) -> bytes:
    """*topic* as RE2 sees it: UTF-8 (a lone surrogate kept, as no pattern can match it)."""
    return topic.encode("utf-8", "surrogatepass")


class TopicIndex:
    """Topics in insertion order, also sorted by UTF-8 bytes for range lookups.

    Adding or removing a topic costs a bisection and a list insert or delete (a memmove
    of at most a few thousand pointers); moving one last costs a dict update.
    """

    __slots__ = ("_keys", "_names", "_order", "_seq")

    def __init__(self) -> None:
        self._order: dict[str, int] = {}  # topic -> sequence number, in insertion order
        self._seq = itertools.count()
        self._keys: list[bytes] = []  # topic_key of every topic, sorted
        self._names: list[str] = []  # the topics, in the order of _keys

    def __len__(self) -> int:
        return len(self._order)

    def __contains__(self, topic: object) -> bool:
        return topic in self._order

    def __iter__(self) -> Iterator[str]:
        """The topics in insertion order (a topic added again counts from then)."""
        return iter(self._order)

    def add(self, topic: str) -> None:
        """Add *topic* last, or move it last if it is here."""
        if topic not in self._order:
            key = topic_key(topic)
            at = bisect.bisect_left(self._keys, key)
            self._keys.insert(at, key)
            self._names.insert(at, topic)
        else:
            del self._order[topic]  # re-inserted below: last in the dict's order
        self._order[topic] = next(self._seq)

    def discard(self, topic: str) -> None:
        """Remove *topic* if it is here."""
        if self._order.pop(topic, None) is None:
            return
        at = bisect.bisect_left(self._keys, topic_key(topic))
        del self._keys[at]
        del self._names[at]

    def oldest(self) -> str:
        """The topic added (or moved last) longest ago.

        Raises:
            StopIteration: The set is empty.
        """
        return next(iter(self._order))

    def candidates(self, patterns: Sequence[FullMatch]) -> list[str]:
        """The topics one of *patterns* may match, in insertion order: every topic one of
        them matches, and for a pattern RE2 bounds loosely, some none does (the caller
        matches them).

        Costs a lookup per literal topic, a bisection per bounded pattern and a sort of
        the candidates, a copy of the set when one pattern is unbounded.
        """
        found: set[str] = set()
        for pattern in patterns:
            literal = pattern.literal
            if literal is not None:
                if literal in self._order:
                    found.add(literal)
                continue
            bounds = pattern.bounds()
            if bounds is None:
                return list(self._order)
            start = bisect.bisect_left(self._keys, bounds[0])
            end = bisect.bisect_right(self._keys, bounds[1])
            if end - start == len(self._keys):  # all of them: already in order
                return list(self._order)
            found.update(self._names[start:end])
        if len(found) == len(self._order):  # all of them: already in order
            return list(self._order)
        return sorted(found, key=self._order.__getitem__)
