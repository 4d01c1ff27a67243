"""Which NATS subjects a replica subscribes to: interest follows local subscriptions.

:class:`Interest` counts local subscriptions, each a pattern and the receive rules of the
connection holding it (several connections may hold the same pair), and answers the
smallest set of subjects that covers what they can be delivered
(:func:`~fleetctl.server.cluster.regexsubjects.narrowed_subjects`: a ``.*`` subscriber
that may receive ``/husky1/.*`` needs ``<prefix>.husky1.>``, not ``<prefix>.>``), merged
by :func:`~fleetctl.server.cluster.subjects.cover`. Pure: the NATS layer diffs the answer
against what it is subscribed to.
"""

from __future__ import annotations

from fleetctl.server.cluster.regexsubjects import narrowed_subjects, regex_subjects
from fleetctl.server.cluster.subjects import cover

# One subscription as the interest counts it: its pattern, and its connection's receive
# rules' regexes (None: not known, the pattern's own subjects).
Held = tuple[str, tuple[str, ...] | None]


class Interest:
    """Reference counts of local subscriptions, and the subjects they need.

    Args:
        prefix: The cluster's subject prefix.

    Attributes:
        counters: Subscriptions (pattern and rules) first held, by what the rules did:
            ``narrowed`` (the rules gave fewer or narrower subjects than the pattern
            alone), ``unchanged``, and ``unclear`` (the pattern or a rule has
            alternatives not split, see
            :mod:`~fleetctl.server.cluster.regexsubjects`: its subjects may be wider than
            needed).
    """

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self._held: dict[Held, tuple[int, frozenset[str]]] = {}  # holders, its subjects
        self._subjects: dict[str, int] = {}
        self.wanted: frozenset[str] = frozenset()
        self.counters = {"narrowed": 0, "unchanged": 0, "unclear": 0}

    def follow(self, pattern: str, delta: int, receive: tuple[str, ...] | None = None) -> bool:
        """Count *pattern*, held by a connection that may receive *receive*, held by one
        more (``+1``) or one fewer (``-1``) connection.

        Returns:
            Whether :attr:`wanted` changed.
        """
        key = (pattern, receive)
        count, subjects = self._held.get(key, (0, frozenset()))
        if count == 0 and delta > 0:
            subjects = self._derive(pattern, receive)
        count += delta
        if count > 0:
            self._held[key] = (count, subjects)
        else:
            self._held.pop(key, None)
        if (count > 0) == (count - delta > 0):  # not its first holder, nor its last
            return False
        for subject in subjects:
            held = self._subjects.get(subject, 0) + (1 if count > 0 else -1)
            if held > 0:
                self._subjects[subject] = held
            else:
                self._subjects.pop(subject, None)
        wanted = cover(self._subjects)
        changed = wanted != self.wanted
        self.wanted = wanted
        return changed

    def _derive(self, pattern: str, receive: tuple[str, ...] | None) -> frozenset[str]:
        derived = narrowed_subjects(self.prefix, pattern, receive)
        if derived.unclear:
            self.counters["unclear"] += 1
        if derived.subjects != regex_subjects(self.prefix, pattern).subjects:
            self.counters["narrowed"] += 1
        else:
            self.counters["unchanged"] += 1
        return derived.subjects
