"""Which NATS subjects a replica subscribes to: interest follows local subscriptions.

:class:`Interest` counts local subscription patterns (several connections may hold the
same one) and answers the smallest set of subjects that covers them
(:func:`~fleetctl.server.cluster.subjects.cover`). Pure: the NATS layer diffs the answer
against what it is subscribed to.
"""

from __future__ import annotations

from fleetctl.server.cluster.subjects import cover, pattern_subject
from fleetctl.server.regex import compile_full


class Interest:
    """Reference counts of local patterns, and the subjects they need.

    Args:
        prefix: The cluster's subject prefix.
    """

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self._patterns: dict[str, int] = {}
        self._subjects: dict[str, int] = {}
        self.wanted: frozenset[str] = frozenset()

    def follow(self, pattern: str, delta: int) -> bool:
        """Count *pattern* held by one more (``+1``) or one fewer (``-1``) connection.

        Returns:
            Whether :attr:`wanted` changed.
        """
        count = self._patterns.get(pattern, 0) + delta
        if count > 0:
            self._patterns[pattern] = count
        else:
            self._patterns.pop(pattern, None)
        if (count > 0) == (count - delta > 0):  # not its first holder, nor its last
            return False
        subject = pattern_subject(self.prefix, pattern, compile_full(pattern).literal)
        held = self._subjects.get(subject, 0) + (1 if count > 0 else -1)
        if held > 0:
            self._subjects[subject] = held
        else:
            self._subjects.pop(subject, None)
        wanted = cover(self._subjects)
        changed = wanted != self.wanted
        self.wanted = wanted
        return changed
