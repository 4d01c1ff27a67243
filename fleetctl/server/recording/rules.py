"""Which frames the recorder takes: RE2 topic rules per sender identity, cached.

The relay asks for every accepted frame, so the answer is cached per (topic, identity
set): a :class:`Permissions` object is shared by every connection with the same identity
set (:class:`fleetctl.server.permissions.PermissionsPool`), which makes it a cheap key.
"""

from __future__ import annotations

from fleetctl.server.permissions import Permissions
from fleetctl.server.recording.config import RecordingRule
from fleetctl.server.regex import FullMatch, compile_full

# Why bounded: topic names come from clients; a client inventing topics only costs a
# cache refill.
MAX_CACHED = 16384


class RecordingRules:
    """Answers "record this topic from these identities?".

    Args:
        rules: The config's rules; a frame is recorded when any matches.
    """

    def __init__(self, rules: tuple[RecordingRule, ...]) -> None:
        self._rules: tuple[tuple[FullMatch, frozenset[str]], ...] = tuple(
            (compile_full(r.topic), frozenset(r.identities)) for r in rules)
        self._cache: dict[tuple[str, Permissions], bool] = {}

    def matches(self, topic: str, perms: Permissions) -> bool:
        """Whether a frame on *topic* sent by a connection with *perms* is recorded."""
        key = (topic, perms)
        cached = self._cache.get(key)
        if cached is None:
            cached = self._decide(topic, frozenset(perms.names))
            if len(self._cache) >= MAX_CACHED:
                self._cache.clear()
            self._cache[key] = cached
        return cached

    def matches_names(self, topic: str, names: frozenset[str]) -> bool:
        """Whether a frame on *topic* sent by identities *names* is recorded (uncached)."""
        return self._decide(topic, names)

    def _decide(self, topic: str, names: frozenset[str]) -> bool:
        return any(regex.matches(topic) and (not who or bool(who & names))
                   for regex, who in self._rules)
