"""Permissions of one connection: the union of its identities' rules, with caches.

A full RE2 match costs microseconds; the relay asks "may X send/receive topic T?" for
every frame and every delivery, so answers are cached per identity set and topic. The
caches are bounded (cleared when full) because topic names come from clients.
"""

from __future__ import annotations

from fleetctl.server.authmap import Identity, Rule

# Why 16384: far more topics than a fleet has; a client inventing topics only costs itself
# a cache refill.
MAX_CACHED_TOPICS = 16384


class Permissions:
    """What a set of identities may send and receive.

    Shared by every connection with the same identity set (see :class:`PermissionsPool`),
    so one robot reconnecting keeps its warm cache.
    """

    __slots__ = ("_receive", "_recv_cache", "_send", "_send_cache", "identities",
                 "receive_patterns")

    def __init__(self, identities: tuple[Identity, ...]) -> None:
        self.identities = identities
        rules = [r for i in identities for r in i.rules]
        self._send = tuple(r.topic for r in rules if r.op.allows_send())
        self._receive = tuple(r.topic for r in rules if r.op.allows_receive())
        # What a replica's NATS interest is narrowed by (cluster/interest.py).
        self.receive_patterns = tuple(m.pattern for m in self._receive)
        self._send_cache: dict[str, bool] = {}
        self._recv_cache: dict[str, bool] = {}

    @property
    def rules(self) -> list[Rule]:
        """Every rule of every identity, in auth-map order."""
        return [r for i in self.identities for r in i.rules]

    @property
    def names(self) -> list[str]:
        """The identity names."""
        return [i.name for i in self.identities]

    @property
    def any_receive(self) -> bool:
        """Whether any rule grants receive on anything."""
        return bool(self._receive)

    def may_send(self, topic: str) -> bool:
        """Return whether these identities may send on *topic* (full match)."""
        cached = self._send_cache.get(topic)
        if cached is None:
            cached = any(m.matches(topic) for m in self._send)
            _store(self._send_cache, topic, cached)
        return cached

    def may_receive(self, topic: str) -> bool:
        """Return whether these identities may receive *topic* (full match)."""
        cached = self._recv_cache.get(topic)
        if cached is None:
            cached = any(m.matches(topic) for m in self._receive)
            _store(self._recv_cache, topic, cached)
        return cached


def _store(cache: dict[str, bool], topic: str, value: bool) -> None:
    if len(cache) >= MAX_CACHED_TOPICS:
        cache.clear()
    cache[topic] = value


class PermissionsPool:
    """Hands out one shared :class:`Permissions` per distinct identity set."""

    def __init__(self) -> None:
        self._pool: dict[tuple[str, ...], Permissions] = {}

    def get(self, identities: list[Identity]) -> Permissions:
        """Return the permissions of *identities* (deduplicated, order kept)."""
        unique: dict[str, Identity] = {}
        for ident in identities:
            unique.setdefault(ident.name, ident)
        key = tuple(unique)
        perms = self._pool.get(key)
        if perms is None:
            perms = Permissions(tuple(unique.values()))
            self._pool[key] = perms
        return perms
