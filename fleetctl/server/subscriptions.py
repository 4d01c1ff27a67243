"""The subscription map S of Robofleet Algorithm 3, with a per-topic receiver cache.

Each connection holds a bounded set of RE2 full-match subscription regexes (bounded in
number and in pattern bytes, per connection and per identity). The relay asks
:meth:`SubscriptionMap.receivers` for every frame; its answer (subscribers whose regex
matches *and* who may receive the topic) is cached per topic, so the steady state costs one
dict lookup and one integer comparison per frame.

A subscription change never walks the cache (up to :data:`MAX_CACHED_TOPICS` topics): a
literal topic's answer is updated at once (one lookup); a pattern change only records
that its connection changed (a version number), and each cached answer is brought up to
date on its topic's next frame by asking again only the connections that changed since
that answer was made (one RE2 call each). Why: matching a pattern against every cached
topic on the event loop cost 19-21 ms a change with 16,000 topics cached, and one token
churning patterns at the control rate stalled the relay (a new client's handshake timed
out after 10 s; docs/security.md). Now a change costs ~8 us, and the catching up is done
only on topics in use. An auth map reload clears the cache. A topic not
cached yet costs one RE2 call per connection (its subscriptions joined,
:class:`~fleetctl.server.regex.AnyOf`), not one per subscription.

What subscriptions just added start delivering (:meth:`SubscriptionMap.newly_matched`,
for the latched messages and keyframe requests a new subscriber gets) is asked of the
stored topics the patterns may match (:class:`~fleetctl.server.topicindex.TopicIndex`),
the patterns in one matcher (a resumed session's all at once), then of the connection's
other subscriptions in one matcher, limited to those that may match the same topics; it
says what that cost, which the relay charges.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Generic, NamedTuple, TypeVar

from fleetctl.server.permissions import Permissions
from fleetctl.server.regex import AnyOf, BadRegex, FullMatch, compile_full

C = TypeVar("C", bound=Hashable)

# Why: topics are client-chosen; a sender inventing topics must not grow the cache forever.
MAX_CACHED_TOPICS = 16384
# Connections whose pattern changes the cached answers may not reflect yet, remembered
# (each with the version of its last change). Past it the oldest is forgotten, and an
# answer older than its change is recomputed whole on its topic's next frame (one RE2 call
# per subscribed connection, as for a new topic). Why a bound: one entry per connection
# that ever changed would grow with every connection that comes and goes.
MAX_PENDING_CHANGES = 1024


# What newly_matched counts as one unit of work when it joins patterns into one matcher:
# quota bytes (FullMatch.cost) of the patterns joined. Why 8: compiling the join took
# 0.07-0.2 us per quota byte here (16 ms for 15 patterns of 4 KiB; 1.7 ms for 255
# `.*zzzN`), a regex call 2-4 us.
QUOTA_BYTES_PER_WORK = 8


# Some patterns of one connection, and one matcher of them all (see _joined).
_Joined = tuple[tuple[str, ...], "FullMatch | AnyOf"]


class Matched(NamedTuple):
    """What :meth:`SubscriptionMap.newly_matched` found.

    Attributes:
        topics: The topics a new subscription starts delivering.
        work: What finding them cost, in units of about one regex call: the candidate
            topics, the topics matched (each asked of the connection's other
            subscriptions in one call) and, when those had to be joined into one matcher,
            their quota bytes / :data:`QUOTA_BYTES_PER_WORK`.
    """

    topics: list[str]
    work: int


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


@dataclass
class _Entry:
    """One connection's subscriptions and what they are charged against."""

    perms: Permissions
    subs: dict[str, FullMatch] = field(default_factory=dict)
    nbytes: int = 0  # quota bytes of the patterns (FullMatch.cost)
    keys: tuple[str, ...] = ()  # identity names the bytes are charged to
    joined: AnyOf | None = None  # all of subs in one matcher; None: build it when asked
    # The last matchers of others_overlapping and of newly_matched's patterns, with the
    # patterns each joins: the stores one subscribe asks (latched, video, other replicas'
    # video) ask with the same patterns, and a churn with the same others.
    others: _Joined | None = None
    new: _Joined | None = None

    def any_matches(self, topic: str) -> bool:
        """Whether any of the subscriptions matches *topic* (one RE2 call, see AnyOf)."""
        joined = self.joined
        if joined is None:
            joined = self.joined = AnyOf(self.subs.values())
        return joined.matches(topic)

    def others_overlapping(self, new: dict[str, FullMatch]
                           ) -> tuple[FullMatch | AnyOf | None, int]:
        """One matcher of the subscriptions not in *new* (some of them, by pattern) that
        may match a topic one of *new* matches (their :meth:`FullMatch.bounds` overlap),
        and the work building it took (see :class:`Matched`; 0 when the last one is
        reused).

        Returns:
            ``(None, 0)`` when there is none: *new* shares no topic with the others.
        """
        ranges = [m.bounds() for m in new.values()]
        overlapping = tuple(p for p, m in self.subs.items() if p not in new
                            and any(_overlap(r, m.bounds()) for r in ranges))
        if not overlapping:
            return None, 0
        self.others, work = _joined(self.others, overlapping, self.subs)
        return self.others[1], work


def _joined(last: _Joined | None, patterns: tuple[str, ...],
            subs: dict[str, FullMatch]) -> tuple[_Joined, int]:
    """*patterns* (keys of *subs*) in one matcher with the patterns it joins, and the work
    of joining them; *last* again, at no work, when it joins the same patterns."""
    if last is not None and last[0] == patterns:
        return last, 0
    matcher, work = _one_matcher([subs[p] for p in patterns])
    return (patterns, matcher), work


def _one_matcher(patterns: list[FullMatch]) -> tuple[FullMatch | AnyOf, int]:
    """*patterns* in one matcher (one pattern: itself), and the work of joining them
    (:class:`Matched`)."""
    if len(patterns) == 1:
        return patterns[0], 0
    joined = [m.cost for m in patterns if m.literal is None]
    work = sum(joined) // QUOTA_BYTES_PER_WORK if len(joined) > 1 else 0
    return AnyOf(patterns), work


def _overlap(a: tuple[bytes, bytes] | None, b: tuple[bytes, bytes] | None) -> bool:
    """Whether two :meth:`FullMatch.bounds` ranges share a topic (``None``: all)."""
    return a is None or b is None or (a[0] <= b[1] and b[0] <= a[1])


class SubscriptionMap(Generic[C]):
    """Subscriptions of every connection.

    Args:
        max_per_connection: Subscriptions one connection may hold.
        max_bytes_per_connection: Pattern bytes (UTF-8) one connection may hold; ``None``
            for no bound.
        max_bytes_per_key: Pattern bytes all connections charged to one key (an identity
            name) may hold together; ``None`` for no bound.
        watch: Called with ``(pattern, receive, +1)`` when a connection whose receive
            rules' regexes are *receive* starts holding a pattern and with ``-1`` when it
            stops, or its rules change (the fan-out's interest, which the rules narrow),
            or ``None``.
    """

    def __init__(self, max_per_connection: int, max_bytes_per_connection: int | None = None,
                 max_bytes_per_key: int | None = None,
                 watch: Callable[[str, tuple[str, ...], int], None] | None = None) -> None:
        self._watch = watch or _ignore
        self.max_per_connection = max_per_connection
        self.max_bytes_per_connection = max_bytes_per_connection
        self.max_bytes_per_key = max_bytes_per_key
        self._subs: dict[C, _Entry] = {}
        # topic -> (version it reflects, receivers); see receivers()
        self._cache: dict[str, tuple[int, tuple[C, ...]]] = {}
        self._key_bytes: dict[str, int] = {}
        self._version = 0  # bumped by each pattern change (_touch)
        # connection -> version of its last pattern change, oldest first (bounded)
        self._changed: dict[C, int] = {}
        self._floor = 0  # answers older than this may miss a forgotten change: recompute

    def __len__(self) -> int:
        return sum(len(e.subs) for e in self._subs.values())

    def patterns(self, conn: C) -> list[str]:
        """Return the subscription regexes of *conn*."""
        entry = self._subs.get(conn)
        return list(entry.subs) if entry else []

    def pattern_bytes(self, conn: C) -> int:
        """Quota bytes of *conn*'s patterns (:attr:`FullMatch.cost`)."""
        entry = self._subs.get(conn)
        return entry.nbytes if entry else 0

    def key_bytes(self, key: str) -> int:
        """Quota bytes of the patterns charged to *key*."""
        return self._key_bytes.get(key, 0)

    def subscribe(self, conn: C, perms: Permissions, pattern: str,
                  keys: Iterable[str] = ()) -> bool:
        """Add a subscription (idempotent).

        A literal topic must be receivable. A pattern is taken if the connection has any
        receive rule; each delivery is then checked against the receive rules.

        Args:
            conn: The connection.
            perms: Its permissions.
            pattern: RE2 full-match regex (or a literal topic).
            keys: Identity names the pattern bytes are charged to.

        Returns:
            ``True`` when the subscription is new, ``False`` when *conn* already held it.

        Raises:
            Refusal: Bad regex, nothing receivable, or over a per-connection or per-key
                bound.
        """
        entry = self._entry(conn, perms, tuple(keys))
        if pattern in entry.subs:
            return False
        size = len(pattern.encode("utf-8", "surrogatepass"))
        self._check_quota(entry, size)  # before compiling: an RE2 compile is the dear part
        try:
            compiled = compile_full(pattern)
        except BadRegex as exc:
            raise Refusal("bad_regex", f"bad RE2 regex {pattern!r:.200}: {exc}") from None
        size = compiled.cost  # its text, or its program when that is larger
        self._check_quota(entry, size)
        refusal = _refusal(perms, pattern, compiled)
        if refusal is not None:
            raise refusal
        entry.subs[pattern] = compiled
        entry.joined = None
        self._charge(entry, size)
        self._watch(pattern, entry.perms.receive_patterns, 1)
        literal = compiled.literal
        if literal is None:  # cached answers catch up on their topic's next frame
            self._touch(conn)
            return True
        cached = self._cache.get(literal)  # a literal can change one answer: at once
        if (cached is not None and conn not in cached[1] and compiled.matches(literal)
                and perms.may_receive(literal)):
            self._cache[literal] = (cached[0], (*cached[1], conn))
        return True

    def _touch(self, conn: C) -> None:
        """Record that *conn*'s patterns (or permissions) changed: every cached answer
        older than now asks *conn* again on its topic's next frame (see receivers)."""
        self._version += 1
        changed = self._changed
        changed.pop(conn, None)  # re-inserted last: the dict stays in version order
        changed[conn] = self._version
        if len(changed) > MAX_PENDING_CHANGES:
            oldest = next(iter(changed))
            self._floor = changed.pop(oldest)

    def newly_matched(self, conn: C, patterns: Sequence[str],
                      candidates: Callable[[Sequence[FullMatch]], list[str]]) -> Matched:
        """The stored topics that *conn* receives through one of *patterns* and through
        none of its other subscriptions: what subscriptions just added (one, or a resumed
        session's) start delivering (the latched messages and keyframe requests a new
        subscriber gets).

        Args:
            conn: The connection.
            patterns: Some of its subscriptions (those it does not hold are ignored).
            candidates: Given the compiled *patterns*, the stored topics one of them may
                match, in the store's order (e.g. :meth:`TopicIndex.candidates`).

        Returns:
            Those topics (none if *conn* holds none of *patterns*), in the candidates'
            order, and the work it took.
        """
        entry = self._subs.get(conn)
        if entry is None:
            return Matched([], 0)
        new = {p: entry.subs[p] for p in patterns if p in entry.subs}
        if not new:
            return Matched([], 0)
        topics = candidates(list(new.values()))
        entry.new, work = _joined(entry.new, tuple(new), entry.subs)
        matcher = entry.new[1]
        may_receive = entry.perms.may_receive
        found = [t for t in topics if matcher.matches(t) and may_receive(t)]
        # One call per candidate; per topic found, one call of the others and a delivery.
        work += len(topics) + len(found)
        if not found:
            return Matched(found, work)
        others, joined_work = entry.others_overlapping(new)
        if others is not None:
            found = [t for t in found if not others.matches(t)]
        return Matched(found, work + joined_work)

    def _entry(self, conn: C, perms: Permissions, keys: tuple[str, ...]) -> _Entry:
        entry = self._subs.get(conn)
        if entry is None:
            entry = self._subs[conn] = _Entry(perms, keys=keys)
        elif entry.perms is not perms:  # its permissions changed: answers may differ
            self._rewatch(entry, perms)
            entry.perms = perms
            self._touch(conn)
        if entry.keys != keys:  # e.g. a token frame added an identity
            self._charge_keys(entry.keys, -entry.nbytes)
            entry.keys = keys
            self._charge_keys(keys, entry.nbytes)
        return entry

    def _check_quota(self, entry: _Entry, size: int) -> None:
        if len(entry.subs) >= self.max_per_connection:
            raise Refusal(
                "too_many_subscriptions",
                f"limit of {self.max_per_connection} subscriptions per connection reached",
            )
        limit = self.max_bytes_per_connection
        if limit is not None and entry.nbytes + size > limit:
            raise Refusal("too_many_subscriptions",
                          f"limit of {limit} pattern bytes per connection reached")
        limit = self.max_bytes_per_key
        full = next((k for k in entry.keys if limit is not None
                     and self._key_bytes.get(k, 0) + size > limit), None)
        if full is not None:
            raise Refusal("too_many_subscriptions",
                          f"limit of {limit} pattern bytes per identity reached ({full!r})")

    def _charge(self, entry: _Entry, size: int) -> None:
        """Add *size* bytes (negative: release) to *entry* and to its keys."""
        entry.nbytes += size
        self._charge_keys(entry.keys, size)

    def _charge_keys(self, keys: tuple[str, ...], size: int) -> None:
        for key in keys:
            left = self._key_bytes.get(key, 0) + size
            if left > 0:
                self._key_bytes[key] = left
            else:
                self._key_bytes.pop(key, None)

    def unsubscribe(self, conn: C, pattern: str) -> bool:
        """Remove a subscription; return whether it existed."""
        entry = self._subs.get(conn)
        if entry is None:
            return False
        compiled = entry.subs.pop(pattern, None)
        if compiled is None:
            return False
        entry.joined = None
        self._charge(entry, -compiled.cost)
        self._watch(pattern, entry.perms.receive_patterns, -1)
        literal = compiled.literal
        if literal is None:  # as in subscribe: answers catch up on their next frame
            self._touch(conn)
            return True
        cached = self._cache.get(literal)
        if cached is not None and conn in cached[1] and not entry.any_matches(literal):
            self._cache[literal] = (cached[0], tuple(c for c in cached[1] if c != conn))
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
        for pattern, compiled in list(entry.subs.items()):
            reason = _refusal(perms, pattern, compiled)
            if reason is not None:
                refused.append((pattern, reason))
                del entry.subs[pattern]
                entry.joined = None
                self._charge(entry, -compiled.cost)
                self._watch(pattern, entry.perms.receive_patterns, -1)
        self._rewatch(entry, perms)
        entry.perms = perms
        self._cache.clear()
        return refused

    def remove(self, conn: C) -> None:
        """Forget every subscription of a closed connection."""
        entry = self._subs.pop(conn, None)
        if entry is None:
            return
        self._charge(entry, -entry.nbytes)
        for pattern in entry.subs:
            self._watch(pattern, entry.perms.receive_patterns, -1)
        self._changed.pop(conn, None)  # in no answer from now on: nothing to catch up
        # At once, not lazily: a cached answer must not keep a closed connection (and
        # what its queue holds) alive until its topic's next frame. One tuple test per
        # cached topic, no regex.
        for topic, (version, found) in self._cache.items():
            if conn in found:
                self._cache[topic] = (version, tuple(c for c in found if c != conn))

    def _rewatch(self, entry: _Entry, perms: Permissions) -> None:
        """*entry*'s patterns are held under *perms* from now on: the interest follows its
        receive rules (the new ones counted before the old ones go, so that a subject
        both need is never let go in between)."""
        old, new = entry.perms.receive_patterns, perms.receive_patterns
        if old == new:
            return
        for pattern in entry.subs:
            self._watch(pattern, new, 1)
        for pattern in entry.subs:
            self._watch(pattern, old, -1)

    def routes(self, topic: str) -> bool:
        """Whether the receivers of *topic* are cached (a frame on it costs a lookup)."""
        return topic in self._cache

    def receivers(self, topic: str) -> tuple[C, ...]:
        """Return the connections that get a frame on *topic* (Algorithm 3 lines 15-16)."""
        cached = self._cache.get(topic)
        if cached is not None:
            version, found = cached
            if version == self._version:  # the steady state
                return found
            if version < self._floor:  # a change it may miss was forgotten
                found = self._compute(topic)
            else:
                found = self._catch_up(topic, version, found)
        else:
            found = self._compute(topic)
            if len(self._cache) >= MAX_CACHED_TOPICS:
                self._cache.clear()
        self._cache[topic] = (self._version, found)
        return found

    def _compute(self, topic: str) -> tuple[C, ...]:
        """Every connection asked: one RE2 call per connection, not one per subscription
        (see AnyOf)."""
        return tuple(conn for conn, entry in self._subs.items()
                     if entry.subs and entry.any_matches(topic)
                     and entry.perms.may_receive(topic))

    def _catch_up(self, topic: str, version: int, found: tuple[C, ...]) -> tuple[C, ...]:
        """*found* (the answer as of *version*) with the connections that changed since
        asked again; the others keep their place."""
        changed: list[C] = []
        for conn, at in reversed(self._changed.items()):  # newest first: stop at *version*
            if at <= version:
                break
            changed.append(conn)
        again = set(changed)
        kept = tuple(c for c in found if c not in again)
        return (*kept, *(c for c in reversed(changed) if self._receives(c, topic)))

    def _receives(self, conn: C, topic: str) -> bool:
        entry = self._subs.get(conn)
        return (entry is not None and bool(entry.subs) and entry.any_matches(topic)
                and entry.perms.may_receive(topic))


def _ignore(pattern: str, receive: tuple[str, ...], delta: int) -> None:
    pass


def _refusal(perms: Permissions, pattern: str, compiled: FullMatch) -> Refusal | None:
    """Why *perms* may not hold the subscription *pattern*, or ``None`` if they may."""
    if compiled.literal is not None and not perms.may_receive(compiled.literal):
        return Refusal("subscription_refused", f"no receive permission on {pattern!r}")
    if compiled.literal is None and not perms.any_receive:
        return Refusal("subscription_refused", "this identity may not receive any topic")
    return None
