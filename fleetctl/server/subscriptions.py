"""The subscription map S of Robofleet Algorithm 3, with a per-topic receiver cache.

Each connection holds a bounded set of RE2 full-match subscription regexes. The relay asks
:meth:`SubscriptionMap.receivers` for every frame; its answer (subscribers whose regex
matches *and* who may receive the topic) is cached per topic and invalidated whenever any
subscription changes, so the steady state costs one dict lookup per frame.
"""

from __future__ import annotations

from collections.abc import Hashable
from typing import Generic, TypeVar

from fleetctl.server.permissions import Permissions
from fleetctl.server.regex import BadRegex, FullMatch, compile_full

C = TypeVar("C", bound=Hashable)

# Why: topics are client-chosen; a sender inventing topics must not grow the cache forever.
MAX_CACHED_TOPICS = 16384


class Refusal(Exception):
    """A subscription the server will not take.

    Attributes:
        code: The error code of the error frame (``bad_regex``, ``subscription_refused``,
            ``too_many_subscriptions``).
        message: Human-readable reason.
    """

    def __init__(self, code: str, message: str) -> None:
        super().__init__(code, message)
        self.code = code
        self.message = message

    def __str__(self) -> str:
        return f"{self.code}: {self.message}"


class SubscriptionMap(Generic[C]):
    """Subscriptions of every connection.

    Args:
        max_per_connection: Subscriptions one connection may hold.
    """

    def __init__(self, max_per_connection: int) -> None:
        self.max_per_connection = max_per_connection
        self._subs: dict[C, tuple[Permissions, dict[str, FullMatch]]] = {}
        self._cache: dict[str, tuple[C, ...]] = {}

    def __len__(self) -> int:
        return sum(len(s) for _, s in self._subs.values())

    def patterns(self, conn: C) -> list[str]:
        """Return the subscription regexes of *conn*."""
        entry = self._subs.get(conn)
        return list(entry[1]) if entry else []

    def subscribe(self, conn: C, perms: Permissions, pattern: str) -> None:
        """Add a subscription (idempotent).

        A literal topic must be receivable. A pattern is taken if the connection has any
        receive rule; each delivery is then checked against the receive rules.

        Raises:
            Refusal: Bad regex, nothing receivable, or over the per-connection limit.
        """
        try:
            compiled = compile_full(pattern)
        except BadRegex as exc:
            raise Refusal("bad_regex", f"bad RE2 regex {pattern!r}: {exc}") from None
        refusal = _refusal(perms, pattern, compiled)
        if refusal is not None:
            raise refusal
        entry = self._subs.get(conn)
        subs = entry[1] if entry is not None else {}
        if entry is None or entry[0] is not perms:  # new, or its permissions changed
            self._subs[conn] = (perms, subs)
            self._cache.clear()
        if pattern in subs:
            return
        if len(subs) >= self.max_per_connection:
            raise Refusal(
                "too_many_subscriptions",
                f"limit of {self.max_per_connection} subscriptions per connection reached",
            )
        subs[pattern] = compiled
        self._cache.clear()

    def unsubscribe(self, conn: C, pattern: str) -> bool:
        """Remove a subscription; return whether it existed."""
        entry = self._subs.get(conn)
        if entry is None or entry[1].pop(pattern, None) is None:
            return False
        self._cache.clear()
        return True

    def set_permissions(self, conn: C, perms: Permissions) -> list[tuple[str, Refusal]]:
        """Give *conn*'s subscriptions new permissions (the auth map was reloaded).

        Every pattern is checked again as :meth:`subscribe` would; refused ones are
        removed. The receiver cache is cleared, so deliveries follow the new permissions
        from the next frame on.

        Returns:
            The removed patterns with the reason, in subscription order.
        """
        entry = self._subs.get(conn)
        if entry is None:
            return []
        refused: list[tuple[str, Refusal]] = []
        kept: dict[str, FullMatch] = {}
        for pattern, compiled in entry[1].items():
            reason = _refusal(perms, pattern, compiled)
            if reason is None:
                kept[pattern] = compiled
            else:
                refused.append((pattern, reason))
        self._subs[conn] = (perms, kept)
        self._cache.clear()
        return refused

    def remove(self, conn: C) -> None:
        """Forget every subscription of a closed connection."""
        if self._subs.pop(conn, None) is not None:
            self._cache.clear()

    def receivers(self, topic: str) -> tuple[C, ...]:
        """Return the connections that get a frame on *topic* (Algorithm 3 lines 15-16)."""
        found = self._cache.get(topic)
        if found is None:
            found = tuple(
                conn
                for conn, (perms, subs) in self._subs.items()
                if any(m.matches(topic) for m in subs.values()) and perms.may_receive(topic)
            )
            if len(self._cache) >= MAX_CACHED_TOPICS:
                self._cache.clear()
            self._cache[topic] = found
        return found


def _refusal(perms: Permissions, pattern: str, compiled: FullMatch) -> Refusal | None:
    """Why *perms* may not hold the subscription *pattern*, or ``None`` if they may."""
    if compiled.literal is not None and not perms.may_receive(compiled.literal):
        return Refusal("subscription_refused", f"no receive permission on {pattern!r}")
    if compiled.literal is None and not perms.any_receive:
        return Refusal("subscription_refused", "this identity may not receive any topic")
    return None
