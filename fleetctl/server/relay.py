"""The relay core: Robofleet Algorithm 3 without I/O.

:class:`RelayCore` is fed frames by the asyncio layer (:mod:`fleetctl.server.app`) and
answers by pushing frames into each :class:`Peer`'s outbound scheduler or by asking the
peer to close. Everything here is synchronous, so tests drive it without sockets.

Hot path (:meth:`RelayCore.on_binary`), per frame: one bounds-checked metadata read, a
cached send-permission lookup, a cached receivers lookup, one scheduler push per
receiver, a few dict increments. No logging, no JSON, no regex in the steady state.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import struct
import time
from collections.abc import Callable
from typing import Any

from fleetctl.server import protocol
from fleetctl.server.authmap import AuthMap, Identity
from fleetctl.server.config import ServerConfig
from fleetctl.server.identity import parse_address
from fleetctl.server.metrics import Metrics
from fleetctl.server.outbound import OutboundScheduler
from fleetctl.server.permissions import Permissions, PermissionsPool
from fleetctl.server.regex import compile_full
from fleetctl.server.registry import RobotRegistry, robot_name
from fleetctl.server.sessions import BadSessionName, Session, SessionTable, check_session_name
from fleetctl.server.sessionstore import SessionStore
from fleetctl.server.subscriptions import Refusal, SubscriptionMap
from fleetctl.wire.errors import WireError
from fleetctl.wire.metadata import field_pos, read_root, table_fields

log = logging.getLogger("fleetctl.server")

SUBSCRIPTION_TOPIC = "/subscriptions"
SUBSCRIPTION_TYPE = "amrl_msgs/msg/RobofleetSubscription"
STATUS_TYPE = "amrl_msgs/msg/RobofleetStatus"
FRAGMENT_TYPE = "fleetctl_msgs/msg/Fragment"
_U64 = struct.Struct("<Q").unpack_from
# Why: per-peer memo tables are keyed by client-chosen topics; keep them small.
_MAX_MEMO = 1024


class Peer:
    """One connection as the relay sees it.

    Args:
        peer_id: Unique number of the connection (logs, metrics).
        address: Address used for identity matching, as text (``None`` if unknown).
        outbound: The connection's scheduler.
        close: Asks the I/O layer to close with ``(code, reason)``.
        session_name: The session the client named on the upgrade, if any (validated
            when the connection authenticates).
        by_address: Whether ``ip``/``cidr`` identities apply to this connection (not on
            the web listener, where people sign in with tokens).

    Attributes:
        token_digests: SHA-256 hex digests of the tokens the connection authenticated
            with (never the tokens): what an auth map reload re-checks it by.
    """

    def __init__(
        self,
        peer_id: int,
        address: str | None,
        outbound: OutboundScheduler,
        close: Callable[[int, str], None],
        session_name: str | None = None,
        by_address: bool = True,
    ) -> None:
        self.peer_id = peer_id
        self.session_name = session_name
        self.session: Session[Peer] | None = None
        self.address = address
        self.by_address = by_address
        self.token_digests: set[str] = set()
        self.outbound = outbound
        self._close = close
        self.perms: Permissions | None = None
        self.identities: list[Identity] = []
        self.is_robot = False
        self.closing = False
        self.malformed_in_row = 0
        self.over_limit_subscriptions = 0
        self.robots: set[str] = set()
        self.topic_robot: dict[str, str | None] = {}
        self.refused_topics: set[str] = set()

    @property
    def label(self) -> str:
        """Short text naming the connection in log lines."""
        names = ",".join(i.name for i in self.identities) or "-"
        return f"conn#{self.peer_id}[{names}@{self.address}]"

    def close(self, code: int, reason: str) -> None:
        """Ask the I/O layer to close this connection (once)."""
        if not self.closing:
            self.closing = True
            self._close(code, reason)


class RelayCore:
    """Routing, permissions and bookkeeping of one server.

    Args:
        config: The server config (limits, no_drop topics).
        auth: The loaded auth map.
        registry: The robot registry.
        metrics: Counters to update.
        clock: Monotonic clock in seconds (session expiry).
    """

    def __init__(
        self,
        config: ServerConfig,
        auth: AuthMap,
        registry: RobotRegistry,
        metrics: Metrics,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        self.limits = config.limits
        self.auth = auth
        self.registry = registry
        self.metrics = metrics
        self.pool = PermissionsPool()
        self.subs: SubscriptionMap[Peer] = SubscriptionMap(
            config.limits.max_subscriptions_per_connection
        )
        self.peers: dict[int, Peer] = {}
        self._no_drop_res = tuple(compile_full(p) for p in config.no_drop_topics)
        self._no_drop_memo: dict[str, bool] = {}
        self._next_id = 0
        self.sessions: SessionTable[Peer] = SessionTable(
            config.limits, _session_store(registry), metrics, clock)
        self.sessions.load(auth, self.pool)

    # -- connection life cycle -------------------------------------------------------

    def new_peer(self, address: str | None, close: Callable[[int, str], None],
                 wake: Callable[[], None] | None, session_name: str | None = None,
                 by_address: bool = True) -> Peer:
        """Create the relay state of a new connection (not yet authenticated).

        *session_name* is the ``X-Fleetctl-Session`` header, if any; *by_address* says
        whether address identities apply (see :class:`Peer`).
        """
        self._next_id += 1
        outbound = OutboundScheduler(
            self.limits.outbound_queue_bytes,
            self.limits.outbound_no_drop_messages,
            wake,
            self.metrics.count_drop,
        )
        peer = Peer(self._next_id, address, outbound, close, session_name, by_address)
        self.peers[peer.peer_id] = peer
        self.metrics.connections_total += 1
        self.metrics.connections_open += 1
        return peer

    def authenticate(self, peer: Peer, identities: list[Identity]) -> bool:
        """Grant *peer* the union of *identities* (added to what it has) and welcome it.

        Returns:
            ``False`` (and closes with 4403) when the peer ends up with no identity.
        """
        merged = {i.name: i for i in peer.identities}
        merged.update({i.name: i for i in identities})
        if not merged:
            self._close(peer, protocol.CLOSE_NO_IDENTITY, "connection matches no identity")
            return False
        peer.identities = list(merged.values())
        peer.perms = self.pool.get(peer.identities)
        peer.is_robot = any(i.by_address for i in peer.identities)
        for pattern in self.subs.patterns(peer):  # re-check: rules changed
            self.subs.unsubscribe(peer, pattern)
            self._subscribe(peer, pattern)
        peer.outbound.push_control(protocol.welcome(peer.perms))
        log.info("%s authenticated", peer.label)
        if peer.session_name is not None and peer.session is None:
            self._attach_session(peer, peer.session_name)
        return True

    def reload_auth(self, auth: AuthMap) -> tuple[int, int]:
        """Switch to a reloaded auth map and re-authorize every open connection.

        Each authenticated connection's identities are recomputed from its address
        (address identities) and its token digests. A connection left with none is closed
        with 4403 and stops receiving at once; the others keep their connection, get the
        new permissions (a new ``welcome`` if its rules changed) and lose the
        subscriptions they may no longer hold (an ``error`` and an ``unsubscribed`` frame
        each). Permission caches and receiver caches are rebuilt; sessions follow
        (:meth:`SessionTable.reauthorize`).

        Returns:
            ``(kept, closed)``: authenticated connections kept and closed.
        """
        self.auth = auth
        self.pool = PermissionsPool()  # the old one caches answers of the old rules
        self.sessions.reauthorize(auth, self.pool)
        kept = closed = 0
        for peer in list(self.peers.values()):
            if peer.perms is None or peer.closing:
                continue  # not authenticated yet: it will be, against the new map
            identities = self.current_identities(peer)
            if identities:
                self._regrant(peer, identities)
                kept += 1
            else:
                self.subs.remove(peer)  # nothing more is queued for it from now on
                self._close(peer, protocol.CLOSE_NO_IDENTITY,
                            "credentials revoked (auth map reloaded)")
                closed += 1
        return kept, closed

    def current_identities(self, peer: Peer) -> list[Identity]:
        """*peer*'s identities under the current auth map: address ones (if they apply to
        it) and those of its token digests, deduplicated by name."""
        found: dict[str, Identity] = {}
        if peer.by_address:
            for ident in self.auth.match_address(parse_address(peer.address)):
                found.setdefault(ident.name, ident)
        for digest in sorted(peer.token_digests):
            by_token = self.auth.match_digest(digest)
            if by_token is not None:
                found.setdefault(by_token.name, by_token)
        return list(found.values())

    def _regrant(self, peer: Peer, identities: list[Identity]) -> None:
        """Give a still-allowed *peer* the permissions of its recomputed *identities*."""
        assert peer.perms is not None
        before = protocol.welcome(peer.perms)
        peer.identities = identities
        peer.perms = self.pool.get(identities)
        peer.is_robot = any(i.by_address for i in identities)
        peer.refused_topics.clear()  # a refused send may be allowed now, and the reverse
        welcome = protocol.welcome(peer.perms)
        if welcome != before:
            peer.outbound.push_control(welcome)
            log.info("%s re-authorized: rules changed", peer.label)
        for pattern, refusal in self.subs.set_permissions(peer, peer.perms):
            self._error(peer, refusal.code, pattern, f"{refusal.message} (auth map reloaded)")
            peer.outbound.push_control(protocol.ack("unsubscribed", pattern))
            if peer.session is not None:
                self.sessions.forget_pattern(peer.session, pattern)

    def close_peer(self, peer: Peer) -> None:
        """Forget a closed connection; count what its scheduler dropped."""
        if self.peers.pop(peer.peer_id, None) is None:
            return
        self.subs.remove(peer)
        if peer.session is not None:
            self._detach_session(peer)
        for name in peer.robots:
            self.registry.detach(name)
        self.metrics.connections_open -= 1

    def _close(self, peer: Peer, code: int, reason: str) -> None:
        if not peer.closing:
            self.metrics.count_close(code)
            log.warning("%s closed %d: %s", peer.label, code, reason)
        peer.close(code, reason)

    # -- frames ---------------------------------------------------------------------

    def on_binary(self, peer: Peer, frame: bytes) -> None:
        """Handle one binary frame from *peer* (Algorithm 3)."""
        perms = peer.perms
        if perms is None:
            self._close(peer, protocol.CLOSE_NO_IDENTITY,
                        "connection matches no identity: send a token frame first")
            return
        try:
            meta, root = read_root(frame)
        except WireError as exc:
            self._malformed(peer, "malformed_frame", None, str(exc))
            return
        peer.malformed_in_row = 0
        topic = meta.topic
        if topic == SUBSCRIPTION_TOPIC:
            self._on_subscription(peer, frame, meta.type)
            return
        if not perms.may_send(topic):
            self._unauthorized(peer, topic)
            return
        self.metrics.count_in(topic, len(frame))
        message_id: int | None = None
        if meta.type == FRAGMENT_TYPE:
            try:
                message_id = _fragment_id(frame, root)
            except WireError as exc:
                self._malformed(peer, "malformed_frame", topic, str(exc))
                return
        self._note_robot(peer, topic, meta.type, frame)
        no_drop = meta.no_drop or self._forced_no_drop(topic)
        for receiver in self.subs.receivers(topic):
            receiver.outbound.push(topic, frame, no_drop, message_id)
        if no_drop and self.sessions.has_offline:
            self.sessions.deliver(topic, frame)

    def on_text(self, peer: Peer, text: str) -> None:
        """Handle one text frame: a token frame or a ``list_robots`` request."""
        try:
            data: Any = json.loads(text) if len(text) <= protocol.MAX_TEXT_CHARS else None
        except ValueError:
            data = None
        if not isinstance(data, dict):
            self._malformed(peer, "malformed_frame", None, "text frame is not a JSON object")
            return
        if "token" in data:
            self.on_token(peer, data["token"], data.get("session"))
        elif data.get("type") == "list_robots" and peer.perms is not None:
            peer.malformed_in_row = 0
            peer.outbound.push_control(json.dumps({"type": "robots",
                                                   "robots": self.robots_for(peer.perms)}))
        elif peer.perms is None:
            self._close(peer, protocol.CLOSE_NO_IDENTITY, "connection matches no identity")
        else:
            self._malformed(peer, "unknown_type", None,
                            "text frames are {'token': ...} or {'type': 'list_robots'}")

    def on_token(self, peer: Peer, token: Any, session: Any = None) -> None:
        """Authenticate *peer* by a token; close with 4401 if it matches no identity.

        *session* (the token frame's ``session`` field) names the connection's session;
        it is taken only before the connection has a session or subscriptions (else 4400).
        """
        identity = self.auth.match_token(token) if isinstance(token, str) and token else None
        if identity is None:
            self.metrics.count_error("bad_token")
            peer.outbound.push_control(protocol.error("bad_token", None, "unknown token"))
            self._close(peer, protocol.CLOSE_BAD_TOKEN, "bad token")
            return
        if session is not None and session != peer.session_name:
            if not isinstance(session, str):
                self._bad_session(peer, "the session name must be a string")
                return
            if peer.session_name is not None or self.subs.patterns(peer):
                self._bad_session(peer, "name the session once, before subscribing")
                return
            peer.session_name = session
        if identity.token_sha256 is not None:  # the hash of *token*: matched by it
            peer.token_digests.add(identity.token_sha256)
        self.authenticate(peer, [identity])

    def robots_for(self, perms: Permissions) -> list[dict[str, Any]]:
        """Robots whose ``/<name>/status`` *perms* may receive, as JSON-ready dicts."""
        names = [n for n in self.registry.names() if perms.may_receive(f"/{n}/status")]
        return self.registry.as_json(names)

    def session_gauges(self) -> list[tuple[str, str, str, dict[str, float]]]:
        """Session gauges for ``/metrics``: sessions by state, mailbox depth per session
        (its mailbox while offline, the part not yet sent once a connection attached)."""
        frames: dict[str, float] = {}
        nbytes: dict[str, float] = {}
        for session in self.sessions:
            peer = session.attached
            if peer is None:
                frames[session.label] = float(len(session.mailbox))
                nbytes[session.label] = float(session.mailbox.nbytes)
            else:
                frames[session.label] = float(peer.outbound.backlog_frames)
                nbytes[session.label] = float(peer.outbound.backlog_bytes)
        offline = self.sessions.offline_count
        return [
            ("fleetctl_sessions", "Named sessions by state.", "state",
             {"online": float(len(self.sessions) - offline), "offline": float(offline)}),
            ("fleetctl_session_mailbox_frames", "no_drop frames held for a session.",
             "session", frames),
            ("fleetctl_session_mailbox_bytes", "Bytes held for a session.", "session", nbytes),
        ]

    # -- sessions -----------------------------------------------------------------------

    def _attach_session(self, peer: Peer, name: str) -> None:
        """Attach an authenticated *peer* to its session: mailbox first, then the
        session's subscriptions, re-checked against the peer's permissions."""
        assert peer.perms is not None
        try:
            check_session_name(name)
        except BadSessionName as exc:
            self._bad_session(peer, str(exc))
            return
        key = (tuple(sorted(i.name for i in peer.identities)), name)
        existing = self.sessions.get(key)
        if existing is not None and existing.attached is not None:
            old = existing.attached
            log.warning("%s takes session %s over from %s", peer.label, existing.label,
                        old.label)
            self.subs.remove(old)
            self._detach_session(old)
            self._close(old, protocol.CLOSE_SESSION_TAKEN_OVER,
                        "session taken over by a newer connection")
        session = self.sessions.attach(key, peer.perms, peer)
        if session is None:
            self._bad_session(peer, f"identity holds {self.limits.max_sessions_per_identity}"
                                    " sessions already")
            return
        resumed = session is existing
        peer.session = session
        backlog = session.mailbox.take()
        patterns = list(session.patterns)
        peer.outbound.track_acks()
        peer.outbound.push_control(protocol.session(name, resumed, len(backlog), patterns))
        peer.outbound.push_backlog(backlog)
        for pattern in patterns:  # the client's own resubscribe is then a no-op
            if self._subscribe(peer, pattern):
                peer.outbound.push_control(protocol.ack("subscribed", pattern))
            else:
                self.sessions.forget_pattern(session, pattern)
        if resumed:
            log.info("%s resumed session %s: %d mailbox frames, %d subscriptions "
                     "(%d frames dropped in total)", peer.label, session.label,
                     len(backlog), len(patterns), session.dropped)

    def _detach_session(self, peer: Peer) -> None:
        """*peer* leaves its session: what it may not have delivered goes to the mailbox."""
        session, peer.session = peer.session, None
        assert session is not None
        self.sessions.detach(session, peer.outbound.take_no_drop())

    def _bad_session(self, peer: Peer, message: str) -> None:
        self._error(peer, "bad_session", None, message)
        self._close(peer, protocol.CLOSE_BAD_SESSION, message[:120])

    # -- helpers ----------------------------------------------------------------------

    def _error(self, peer: Peer, code: str, topic: str | None, message: str) -> None:
        self.metrics.count_error(code)
        peer.outbound.push_control(protocol.error(code, topic, message))

    def _malformed(self, peer: Peer, code: str, topic: str | None, message: str) -> None:
        self._error(peer, code, topic, message)
        peer.malformed_in_row += 1
        if peer.malformed_in_row >= self.limits.max_malformed_in_row:
            self._close(peer, protocol.CLOSE_MALFORMED,
                        f"{peer.malformed_in_row} malformed frames in a row")

    def _unauthorized(self, peer: Peer, topic: str) -> None:
        # Answer (and log) once per topic per connection: a misconfigured robot sends at
        # sensor rate, and each refusal is still counted in the metrics.
        self.metrics.count_error("unauthorized_send")
        if topic in peer.refused_topics or len(peer.refused_topics) >= _MAX_MEMO:
            return
        peer.refused_topics.add(topic)
        log.warning("%s may not send on %r", peer.label, topic)
        peer.outbound.push_control(
            protocol.error("unauthorized_send", topic, f"no send permission on {topic!r}")
        )

    def _forced_no_drop(self, topic: str) -> bool:
        if not self._no_drop_res:
            return False
        forced = self._no_drop_memo.get(topic)
        if forced is None:
            forced = any(m.matches(topic) for m in self._no_drop_res)
            if len(self._no_drop_memo) >= 16 * _MAX_MEMO:
                self._no_drop_memo.clear()
            self._no_drop_memo[topic] = forced
        return forced

    def _note_robot(self, peer: Peer, topic: str, type_name: str, frame: bytes) -> None:
        is_status = type_name == STATUS_TYPE
        if not (peer.is_robot or is_status):
            return
        name = peer.topic_robot.get(topic, "")
        if name == "":
            name = robot_name(topic)
            if len(peer.topic_robot) < _MAX_MEMO:
                peer.topic_robot[topic] = name
        if name is None or not self.registry.seen(name):
            return
        if name not in peer.robots:
            peer.robots.add(name)
            self.registry.attach(name)
        if is_status and topic == f"/{name}/status":
            status = protocol.decode_status_fields(frame)
            if status is None:
                self._error(peer, "malformed_frame", topic, "RobofleetStatus does not decode")
            else:
                self.registry.set_status(name, *status)

    def _on_subscription(self, peer: Peer, frame: bytes, type_name: str) -> None:
        # Sending on /subscriptions needs no rule (docs/design.md section 3).
        if type_name != SUBSCRIPTION_TYPE:
            self._malformed(peer, "unknown_type", SUBSCRIPTION_TOPIC,
                            f"/subscriptions carries RobofleetSubscription, not {type_name}")
            return
        fields = protocol.decode_subscription_fields(frame)
        if fields is None:
            self._malformed(peer, "malformed_frame", SUBSCRIPTION_TOPIC,
                            "RobofleetSubscription does not decode")
            return
        pattern, subscribe = fields
        if not subscribe:
            self.subs.unsubscribe(peer, pattern)
            if peer.session is not None:
                self.sessions.unsubscribed(peer.session, pattern)
            peer.outbound.push_control(protocol.ack("unsubscribed", pattern))
        elif self._subscribe(peer, pattern):
            if peer.session is not None:
                self.sessions.subscribed(peer.session, pattern)
            peer.outbound.push_control(protocol.ack("subscribed", pattern))

    def _subscribe(self, peer: Peer, pattern: str) -> bool:
        assert peer.perms is not None
        try:
            self.subs.subscribe(peer, peer.perms, pattern)
        except Refusal as refusal:
            self._error(peer, refusal.code, pattern, refusal.message)
            if refusal.code == "too_many_subscriptions":
                peer.over_limit_subscriptions += 1
                if peer.over_limit_subscriptions > self.limits.max_subscriptions_per_connection:
                    self._close(peer, protocol.CLOSE_SUBSCRIPTION_FLOOD,
                                "subscription flood past the limit")
            return False
        return True


def _session_store(registry: RobotRegistry) -> SessionStore | None:
    try:
        return SessionStore(registry.db)
    except sqlite3.Error:  # sessions then live in memory only; the relay still runs
        log.exception("cannot open the sessions table: sessions will not survive a restart")
        return None


def _fragment_id(frame: bytes, root: int) -> int:
    """Return ``message_id`` (field 1, ulong) of a Fragment root table."""
    n = len(frame)
    vt, vt_bytes, t_bytes = table_fields(frame, root, n)
    pos = field_pos(frame, root, vt, vt_bytes, 1)
    if not pos:
        return 0  # FlatBuffers omits default values: message_id 0
    if pos + 8 > root + t_bytes:
        raise WireError(f"malformed frame: Fragment.message_id outside its table at byte {pos}")
    value: int = _U64(frame, pos)[0]
    return value
