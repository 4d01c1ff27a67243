"""Named sessions: subscriptions that outlive a connection, and bounded mailboxes.

MQTT-style persistent sessions, bounded (docs/server.md, "Sessions"). A client names a
session on the upgrade (``X-Fleetctl-Session: NAME``) or in its first token frame
(``{"token": ..., "session": NAME}``). The session key is ``(identities, name)``: the
sorted names of the auth-map identities the connection matched, and the name; so a client
can only reach sessions of its own identity set.

- The session's subscription patterns are stored in SQLite, written behind
  (:meth:`SessionTable.take_changes` / :meth:`SessionTable.flush`; the server writes them
  in a worker thread about once a second) and survive server restarts.
- While the session has no connection (it dropped, or the server restarted), every
  no_drop frame matching one of its patterns that its identities may receive goes into
  its :class:`Mailbox` (bounded in frames and bytes; overflow drops the oldest, counted).
  Droppable frames are not kept: they resume fresh.
- A session with no pattern is no session: unsubscribing the last pattern (which is what
  a client's clean goodbye does) ends it, and a connection that closes without patterns
  leaves nothing behind. A session offline longer than ``session_expiry_s`` is dropped.

This module holds the state; :class:`~fleetctl.server.relay.RelayCore` drives it (attach
on authentication, detach on close, :meth:`SessionTable.deliver` for no_drop frames).
Nothing here does I/O except the store.
"""

from __future__ import annotations

import hashlib
import logging
import re
import sqlite3
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Generic, TypeVar

from fleetctl.server.authmap import AuthMap
from fleetctl.server.config import ServerLimits
from fleetctl.server.metrics import Metrics
from fleetctl.server.permissions import Permissions, PermissionsPool
from fleetctl.server.sessionstore import SessionStore
from fleetctl.server.subscriptions import Refusal, SubscriptionMap

if TYPE_CHECKING:
    from fleetctl.server.cluster.sharedsessions import SharedSessions

log = logging.getLogger("fleetctl.server")

SESSION_HEADER = "X-Fleetctl-Session"
# ``X-Fleetctl-Standby: 1`` on an upgrade (with SESSION_HEADER): a robot's idle standby
# connection, attached to its session only when it sends ``{"type": "activate"}``. Every
# 101 of the relay carries it too: the server takes standby connections.
STANDBY_HEADER = "X-Fleetctl-Standby"
MAX_SESSION_NAME_CHARS = 64
_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.@:-]{0,63}")

C = TypeVar("C")
SessionKey = tuple[tuple[str, ...], str]


class BadSessionName(ValueError):
    """A session name the server does not take (the message says why)."""


def check_session_name(value: object) -> str:
    """Return *value* if it is a valid session name.

    Valid: 1 to 64 characters of ``A-Z a-z 0-9 _ . @ : -``, starting with a letter or a
    digit (robot names, e-mail-like operator names and host:port fit).

    Raises:
        BadSessionName: Anything else.
    """
    if isinstance(value, str) and _NAME_RE.fullmatch(value):
        return value
    shown = repr(value)[:80]
    raise BadSessionName(
        f"bad session name {shown}: 1-{MAX_SESSION_NAME_CHARS} characters of "
        "A-Z a-z 0-9 _ . @ : - starting with a letter or digit")


def session_label(key: SessionKey) -> str:
    """``identity[+identity...]/name``: the session in log lines."""
    return f"{'+'.join(key[0])}/{key[1]}"


def session_metric_id(key: SessionKey) -> str:
    """``session#1a2b3c4d5e6f``: the session in metric labels, opaque (identity names are
    e-mail addresses; ``/metrics`` must not list who uses the fleet) and stable across
    restarts. Log lines name both (:func:`session_label` and this)."""
    digest = hashlib.sha256(session_label(key).encode("utf-8", "backslashreplace"))
    return f"session#{digest.hexdigest()[:12]}"


class Mailbox:
    """The no_drop frames an offline session missed, oldest first.

    Args:
        max_messages: Frames held at most (>= 1).
        max_bytes: Bytes held at most; an empty mailbox still takes one larger frame.
        on_drop: Called with the topic of every frame dropped to make room.
    """

    __slots__ = ("_on_drop", "frames", "max_bytes", "max_messages", "nbytes")

    def __init__(self, max_messages: int, max_bytes: int,
                 on_drop: Callable[[str], None]) -> None:
        self.max_messages = max_messages
        self.max_bytes = max_bytes
        self._on_drop = on_drop
        self.frames: deque[tuple[str, bytes]] = deque()
        self.nbytes = 0

    def __len__(self) -> int:
        return len(self.frames)

    def put(self, topic: str, frame: bytes) -> None:
        """Append a frame; drop the oldest (counted) until it fits both bounds."""
        size = len(frame)
        frames = self.frames
        while frames and (len(frames) >= self.max_messages
                          or self.nbytes + size > self.max_bytes):
            old_topic, old = frames.popleft()
            self.nbytes -= len(old)
            self._on_drop(old_topic)
        frames.append((topic, frame))
        self.nbytes += size

    def take(self) -> deque[tuple[str, bytes]]:
        """Remove and return every frame, oldest first."""
        frames, self.frames, self.nbytes = self.frames, deque(), 0
        return frames


class Session(Generic[C]):
    """One named session.

    Attributes:
        key: ``(sorted identity names, name)``.
        label: :func:`session_label` of the key (logs).
        metric_id: :func:`session_metric_id` of the key (metrics).
        perms: What the key's identities may receive (checked per mailboxed frame).
        patterns: Subscription regexes, in subscription order (a dict used as an
            ordered set).
        mailbox: Frames kept while offline (empty while a connection is attached: the
            relay moves it into the connection's outbound scheduler on attach).
        attached: The connection using the session, or ``None`` (offline).
        offline_since_s: Monotonic time it went offline (``None`` while attached).
        dropped: Mailbox frames dropped in total; ``overflowing``: dropped since the last
            attach (the overflow is logged once per offline episode).
    """

    __slots__ = ("attached", "dropped", "key", "label", "mailbox", "metric_id",
                 "offline_since_s", "overflowing", "patterns", "perms", "resumed")

    def __init__(self, key: SessionKey, perms: Permissions, mailbox: Mailbox) -> None:
        self.key = key
        self.label = session_label(key)
        self.metric_id = session_metric_id(key)
        self.perms = perms
        self.patterns: dict[str, None] = {}
        self.mailbox = mailbox
        self.attached: C | None = None
        self.offline_since_s: float | None = None
        self.dropped = 0
        self.overflowing = 0
        self.resumed = False


class SessionTable(Generic[C]):
    """Every named session of the server, online and offline.

    Args:
        limits: Mailbox bounds, expiry, sessions per identity, subscriptions per session.
        store: Where patterns persist; ``None`` keeps them in memory only.
        metrics: Mailbox drops are counted here per session and topic.
        clock: Monotonic clock in seconds (expiry).
    """

    def __init__(self, limits: ServerLimits, store: SessionStore | None, metrics: Metrics,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.limits = limits
        self._store = store
        self._metrics = metrics
        self._clock = clock
        self._sessions: dict[SessionKey, Session[C]] = {}
        self._per_identity: dict[tuple[str, ...], int] = {}
        # Write-behind: the latest patterns of each changed session (None: delete it).
        # Bounded by the number of sessions.
        self._changes: dict[SessionKey, tuple[str, ...] | None] = {}
        # Offline sessions' patterns, with the same receiver cache the live map has.
        self._offline: SubscriptionMap[Session[C]] = SubscriptionMap(
            limits.max_subscriptions_per_connection)
        self._offline_count = 0
        # Read by the relay's hot path: any offline session to mailbox for?
        self.has_offline = False
        # In a cluster: the replicas' shared records and stream (set by the relay core);
        # offline sessions then live there only, with no mailbox here.
        self.shared: SharedSessions | None = None

    def __len__(self) -> int:
        return len(self._sessions)

    def __iter__(self) -> Iterator[Session[C]]:
        return iter(list(self._sessions.values()))

    @property
    def offline_count(self) -> int:
        """Sessions without a connection."""
        return self._offline_count

    def get(self, key: SessionKey) -> Session[C] | None:
        """The session of *key*, or ``None``."""
        return self._sessions.get(key)

    # -- life cycle -----------------------------------------------------------------------

    def load(self, auth: AuthMap, pool: PermissionsPool) -> None:
        """Load the stored sessions as offline (their expiry clock starts now).

        A session whose identities are no longer all in the auth map is deleted; a pattern
        its identities may no longer subscribe is dropped from it.
        """
        if self._store is None:
            return
        try:
            stored = self._store.load()
        except sqlite3.Error:
            log.exception("cannot load sessions from the database: starting without them")
            return
        by_name = {i.name: i for i in auth.identities}
        for row in stored:
            key = (row.identities, row.name)
            identities = [by_name[n] for n in row.identities if n in by_name]
            if len(identities) != len(row.identities) or not row.identities:
                log.info("session %s dropped: its identities changed in the auth map",
                         session_label(key))
                self._persist_delete(key)
                continue
            session = self._new(key, pool.get(identities))
            session.patterns = dict.fromkeys(row.patterns)
            self._go_offline(session)
        if self._sessions:
            log.info("loaded %d sessions from the database", len(self._sessions))

    def reauthorize(self, auth: AuthMap, pool: PermissionsPool) -> None:
        """Apply a reloaded auth map to every session.

        A session's permissions become those of its key's identities in *auth*. An offline
        session whose identities are no longer all in *auth* is dropped (with its
        mailbox, counted as drops); an offline session's patterns it may no longer
        subscribe are dropped. An online session whose identities are gone keeps its
        connection (the relay decides about that) but gets no permission, so nothing of
        it survives the connection going offline.
        """
        by_name = {i.name: i for i in auth.identities}
        for session in list(self._sessions.values()):
            names = session.key[0]
            complete = all(n in by_name for n in names)
            if not complete and session.attached is None:
                log.info("session %s dropped: its identities changed in the auth map "
                         "(%d mailbox frames dropped)", session.label, len(session.mailbox))
                self._drop(session)
                continue
            session.perms = pool.get([by_name[n] for n in names] if complete else [])
            if session.attached is None:
                self._recheck_offline(session)

    def _recheck_offline(self, session: Session[C]) -> None:
        for pattern, refusal in self._offline.set_permissions(session, session.perms):
            log.info("session %s: pattern %r dropped after the auth map reload: %s",
                     session.label, pattern, refusal)
            self.forget_pattern(session, pattern)
        if not session.patterns:
            self._forget(session)

    def attach(self, key: SessionKey, perms: Permissions, conn: C) -> Session[C] | None:
        """Attach *conn* to the session of *key*, creating it if needed.

        The caller must have detached a previous connection first (takeover). The
        session's mailbox is left for the caller to move into *conn*'s queue.

        Returns:
            The session, or ``None`` when its identities already hold
            ``max_sessions_per_identity`` sessions.
        """
        session = self._sessions.get(key)
        if session is None:
            shared = self.shared
            record = shared.lookup(key) if shared is not None else None
            held = (shared.count(key[0]) if shared is not None
                    else self._per_identity.get(key[0], 0))
            if record is None and held >= self.limits.max_sessions_per_identity:
                return None
            session = self._new(key, perms)
            session.resumed = record is not None
            if record is not None:
                session.patterns = dict.fromkeys(record.patterns)
        else:
            session.resumed = True
            self._set_online(session)
        assert session.attached is None, "detach the previous connection first"
        session.attached = conn
        session.overflowing = 0
        return session

    def detach(self, session: Session[C], leftovers: Iterable[tuple[str, bytes]]) -> None:
        """The connection of *session* is gone; *leftovers* (no_drop frames it may not
        have delivered, in order) go into the mailbox. A session without patterns ends.
        """
        session.attached = None
        if not session.patterns or self.shared is not None:  # shared: kept by the replicas
            self._forget(session)
            return
        mailbox = session.mailbox
        for topic, frame in leftovers:
            mailbox.put(topic, frame)
        self._go_offline(session)

    def subscribed(self, session: Session[C], pattern: str) -> None:
        """The session's connection subscribed *pattern* (persisted if new)."""
        if pattern not in session.patterns:
            session.patterns[pattern] = None
            self._persist(session)

    def unsubscribed(self, session: Session[C], pattern: str) -> None:
        """The session's connection unsubscribed *pattern*; the last one ends the session."""
        if pattern not in session.patterns:
            return
        self.forget_pattern(session, pattern)
        if not session.patterns:
            log.info("session %s ended: no subscription left", session.label)

    def forget_pattern(self, session: Session[C], pattern: str) -> None:
        """Drop *pattern* from *session* (persisted); without patterns it is stored no more."""
        if pattern not in session.patterns:
            return
        del session.patterns[pattern]
        if session.patterns:
            self._persist(session)
        else:
            self._persist_delete(session.key)

    def expire(self) -> int:
        """Drop sessions offline for longer than ``session_expiry_s``; return how many."""
        if not self._offline_count:
            return 0
        deadline = self._clock() - self.limits.session_expiry_s
        old = [s for s in self._sessions.values()
               if s.offline_since_s is not None and s.offline_since_s < deadline]
        for session in old:
            log.info("session %s expired after %.0f s offline (%d mailbox frames dropped)",
                     session.label, self.limits.session_expiry_s, len(session.mailbox))
            self._drop(session)
        return len(old)

    # -- hot path -------------------------------------------------------------------------

    def deliver(self, topic: str, frame: bytes) -> None:
        """Mailbox a no_drop frame for every offline session that subscribed to *topic*
        and may receive it (call only when :attr:`has_offline`)."""
        for session in self._offline.receivers(topic):
            session.mailbox.put(topic, frame)

    # -- helpers --------------------------------------------------------------------------

    def _new(self, key: SessionKey, perms: Permissions) -> Session[C]:
        session: Session[C] = Session(key, perms, Mailbox(
            self.limits.session_mailbox_messages, self.limits.session_mailbox_bytes,
            lambda topic: self._on_drop(session, topic)))
        self._sessions[key] = session
        self._per_identity[key[0]] = self._per_identity.get(key[0], 0) + 1
        return session

    def _go_offline(self, session: Session[C]) -> None:
        for pattern in list(session.patterns):
            try:
                self._offline.subscribe(session, session.perms, pattern)
            except Refusal as refusal:  # e.g. the auth map changed since it subscribed
                log.info("session %s: pattern %r not kept while offline: %s",
                         session.label, pattern, refusal)
                self.forget_pattern(session, pattern)
        if not session.patterns:
            self._forget(session)
            return
        session.offline_since_s = self._clock()
        self._offline_count += 1
        self.has_offline = True

    def _set_online(self, session: Session[C]) -> None:
        self._offline.remove(session)
        if session.offline_since_s is not None:
            session.offline_since_s = None
            self._offline_count -= 1
            self.has_offline = self._offline_count > 0

    def _drop(self, session: Session[C]) -> None:
        """End an offline session now: its mailbox frames count as drops."""
        for topic, _ in session.mailbox.take():
            self._on_drop(session, topic, overflow=False)
        self._persist_delete(session.key)
        self._forget(session)

    def _forget(self, session: Session[C]) -> None:
        self._set_online(session)
        if self._sessions.pop(session.key, None) is None:
            return
        left = self._per_identity.get(session.key[0], 0) - 1
        if left > 0:
            self._per_identity[session.key[0]] = left
        else:
            self._per_identity.pop(session.key[0], None)

    def _on_drop(self, session: Session[C], topic: str, overflow: bool = True) -> None:
        session.dropped += 1
        self._metrics.count_session_drop(session.metric_id, topic)
        if not overflow:
            return
        session.overflowing += 1
        if session.overflowing == 1:
            log.warning("session %s: mailbox full (%d frames / %d bytes): dropping the "
                        "oldest no_drop frames (first: %s)", session.label,
                        self.limits.session_mailbox_messages,
                        self.limits.session_mailbox_bytes, topic)

    # -- persistence (write-behind) -----------------------------------------------------

    def take_changes(self) -> Callable[[], None] | None:
        """Take the changes not yet stored; return the job that stores them (one
        transaction; safe to run in a worker thread while the relay goes on), or ``None``
        when there is nothing to store.

        The store's database connection must then be used by nobody else until the job
        has run (the server runs it and the robot registry's write in one worker call).
        """
        if self._store is None or not self._changes:
            return None
        changes = [(k[0], k[1], p) for k, p in self._changes.items()]
        self._changes = {}
        store = self._store

        def job() -> None:
            try:
                store.write(changes)
            except sqlite3.Error:  # a full disk must not stop the relay
                log.exception("cannot store %d session changes", len(changes))

        return job

    def flush(self) -> None:
        """Store the pending changes now, on this thread (shutdown, tests)."""
        job = self.take_changes()
        if job is not None:
            job()

    def _persist(self, session: Session[C]) -> None:
        if self.shared is not None:
            self.shared.changed(session.key)
        elif self._store is not None:
            self._changes[session.key] = tuple(session.patterns)

    def _persist_delete(self, key: SessionKey) -> None:
        if self.shared is not None:
            self.shared.changed(key)  # deleted when its connection leaves without patterns
        elif self._store is not None:
            self._changes[key] = None
