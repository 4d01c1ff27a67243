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
import math
import sqlite3
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from fleetctl.server import firstframes, protocol, reauth
from fleetctl.server.admission import IdentityConnections, TokenBucket
from fleetctl.server.authmap import AuthMap, Identity
from fleetctl.server.config import ServerConfig
from fleetctl.server.expectedrobots import expected_robots, never_connected
from fleetctl.server.fanout import Fanout, LocalFanout
from fleetctl.server.keyframes import VIDEO_TYPE, KeyframeRouter
from fleetctl.server.latched import LatchedStore
from fleetctl.server.loginbudget import FailedLogins
from fleetctl.server.metrics import Metrics
from fleetctl.server.outbound import OutboundScheduler
from fleetctl.server.peer import Peer
from fleetctl.server.permissions import Permissions, PermissionsPool
from fleetctl.server.regex import compile_full
from fleetctl.server.registry import RobotRegistry, robot_name
from fleetctl.server.sessions import (
    BadSessionName,
    Session,
    SessionKey,
    SessionTable,
    check_session_name,
    session_label,
)
from fleetctl.server.sessionstore import SessionStore
from fleetctl.server.subscriptions import Refusal, SubscriptionMap
from fleetctl.server.topicindex import TopicIndex
from fleetctl.wire.control import KEYFRAME_REQUESTS_TOPIC
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import read_fragment_id
from fleetctl.wire.metadata import read_root

if TYPE_CHECKING:
    from fleetctl.server.cluster.sharedsessions import SharedSessions
    from fleetctl.server.cluster.storeacks import StoreAcks
    from fleetctl.server.foxglove.catalog import TopicCatalog
    from fleetctl.server.recording.recorder import Recorder

log = logging.getLogger("fleetctl.server")

SUBSCRIPTION_TOPIC = "/subscriptions"
SUBSCRIPTION_TYPE = "amrl_msgs/msg/RobofleetSubscription"
STATUS_TYPE = "amrl_msgs/msg/RobofleetStatus"
FRAGMENT_TYPE = "fleetctl_msgs/msg/Fragment"
# Why: per-peer memo tables are keyed by client-chosen topics; keep them small.
_MAX_MEMO = 1024

# Control requests an identity set may make at once: a full resubscribe of every tab or
# robot connection after a reconnect (at least max_subscriptions_per_connection).
MIN_CONTROL_BURST = 64

# New topics a sender's identity set may start using: a frame on a topic the relay has not
# routed yet (not in the receiver cache) costs one regex call per subscribed connection
# and new permission, metrics and catalog entries, ~10x a frame on a known topic: a robot
# inventing a topic per frame beside 40 subscribed connections put a 200 Hz pair's p50 at
# 324 ms (40 ms for the same flood on one topic). The burst covers a fleet of robots
# sharing one cidr identity coming back after a restart (100 robots x 30 topics); past
# it, such a frame is dropped (counted, one error frame per connection).
NEW_TOPICS_PER_S = 200.0
NEW_TOPICS_BURST = 4096

__all__ = ["Peer", "RelayCore"]


class RelayCore:
    """Routing, permissions and bookkeeping of one server.

    Args:
        config: The server config (limits, no_drop topics).
        auth: The loaded auth map.
        registry: The robot registry.
        metrics: Counters to update.
        clock: Monotonic clock in seconds (session expiry).
        recorder: Takes every accepted frame its rules match (MCAP recording), or
            ``None``.
    """

    def __init__(
        self,
        config: ServerConfig,
        auth: AuthMap,
        registry: RobotRegistry,
        metrics: Metrics,
        clock: Callable[[], float] = time.monotonic,
        recorder: Recorder | None = None,
    ) -> None:
        self.config = config
        self.recorder = recorder
        self.limits = limits = config.limits
        self.auth = auth
        # The robots the auth map expects (expectedrobots), for the one it was read from.
        self._expected: tuple[AuthMap, tuple[str, ...]] = (auth, expected_robots(auth))
        self.registry = registry
        self.metrics = metrics
        self.pool = PermissionsPool()
        self.subs: SubscriptionMap[Peer] = SubscriptionMap(
            limits.max_subscriptions_per_connection,
            limits.max_pattern_bytes_per_connection,
            limits.max_pattern_bytes_per_identity,
            watch=self._follow,
        )
        self.connections = IdentityConnections(limits.max_connections_per_identity)
        # Control requests, per identity set (a reconnect gets no fresh bucket). Bounded
        # by the identity sets that connect, i.e. by the auth map.
        self._buckets: dict[tuple[str, ...], TokenBucket] = {}
        self._topic_buckets: dict[tuple[str, ...], TokenBucket] = {}  # NEW_TOPICS_PER_S
        self._clock = clock
        # Failed logins per client address: past the budget, tokens are refused unhashed.
        self.logins = FailedLogins(clock=clock)
        self.peers: dict[int, Peer] = {}
        # Robots' standby connections (X-Fleetctl-Standby), at most one per session key:
        # a newer one closes the older. An entry leaves when its peer closes or activates.
        self.standbys: dict[SessionKey, Peer] = {}
        self._no_drop_res = tuple(compile_full(p) for p in config.no_drop_topics)
        self._no_drop_memo: dict[str, bool] = {}
        self._next_id = 0
        # A cluster keeps sessions in NATS (use_shared_sessions), not in SQLite.
        self.sessions: SessionTable[Peer] = SessionTable(
            config.limits, _session_store(registry) if config.cluster is None else None,
            metrics, clock)
        self.sessions.load(auth, self.pool)
        # The default fan-out; RelayServer swaps in a NATS one for a cluster (use_fanout).
        self.local = LocalFanout(self.subs, self.sessions)
        self.fanout: Fanout = self.local
        # A cluster's store counters (use_shared_sessions): a sender's pong waits for its
        # no_drop frames to be stored. None: one process, pongs at once.
        self.store_acks: StoreAcks | None = None
        self.latched = LatchedStore(limits.latched_bytes, limits.latched_message_bytes, metrics)
        self.keyframes: KeyframeRouter[Peer] = KeyframeRouter(
            limits.keyframe_request_interval_s, clock, metrics)
        # Video topics whose publisher is on another replica (their frames came through
        # NATS): a new subscription asks those replicas for a keyframe. Bounded.
        self.remote_video = TopicIndex()
        # Which topics exist (Foxglove's channels); set by the Foxglove adapter.
        self.catalog: TopicCatalog | None = None

    # -- connection life cycle -------------------------------------------------------

    def new_peer(self, address: str | None, close: Callable[[int, str], None],
                 wake: Callable[[], None] | None, session_name: str | None = None,
                 by_address: bool = True, standby: bool = False) -> Peer:
        """Create the relay state of a new connection (not yet authenticated).

        *session_name* is the ``X-Fleetctl-Session`` header, if any; *by_address* says
        whether address identities apply (see :class:`Peer`); *standby* is
        ``X-Fleetctl-Standby: 1`` (needs *session_name*; see :meth:`activate`).
        """
        assert not standby or session_name is not None, "a standby names its session"
        self._next_id += 1
        outbound = OutboundScheduler(
            self.limits.outbound_queue_bytes,
            self.limits.outbound_no_drop_messages,
            wake,
            self.metrics.count_drop,
            self.limits.latched_bytes,
        )
        peer = Peer(self._next_id, address, outbound, close, session_name, by_address,
                    standby)
        self.peers[peer.peer_id] = peer
        self.metrics.connections_total += 1
        self.metrics.connections_open += 1
        return peer

    def authenticate(self, peer: Peer, identities: list[Identity]) -> bool:
        """Grant *peer* the union of *identities* (added to what it has) and welcome it.

        Returns:
            ``False`` when the peer ends up with no identity (closed with 4403) or one of
            its identities is at ``max_connections_per_identity`` (closed with 4429).
        """
        merged = {i.name: i for i in peer.identities}
        merged.update({i.name: i for i in identities})
        if not merged:
            self.close_with(peer, protocol.CLOSE_NO_IDENTITY, "connection matches no identity")
            return False
        full = self.connections.full(n for n in merged if n not in peer.counted)
        if full is not None:
            self.close_with(peer, protocol.CLOSE_TOO_MANY, f"identity {full!r} has "
                            f"{self.limits.max_connections_per_identity} connections open")
            return False
        first = peer.perms is None
        before = peer.perms
        peer.identities = list(merged.values())
        peer.perms = self.pool.get(peer.identities)
        peer.is_robot = any(i.by_address for i in peer.identities)
        self.recount(peer)
        if before is not None and peer.perms is not before:  # rules grew: re-check
            for pattern, refusal in self.subs.set_permissions(peer, peer.perms):
                self.send_error(peer, refusal.code, pattern, refusal.message)
        peer.outbound.push_control(protocol.welcome(peer.perms))
        log.info("%s authenticated (metrics: %s)", peer.label, peer.metric_label)
        if first and peer.on_authenticated is not None:
            peer.on_authenticated()
        if peer.session_name is not None and peer.session is None:
            if peer.standby:  # attached when it activates
                self.register_standby(peer)
            else:
                self._attach_session(peer, peer.session_name)
        return True

    def recount(self, peer: Peer) -> None:
        """Count *peer* under its current identity names (the per-identity cap)."""
        self.connections.remove(peer.counted)
        peer.counted = peer.identity_names
        self.connections.add(peer.counted)

    def reload_auth(self, auth: AuthMap) -> tuple[int, int]:
        """Switch to a reloaded auth map and re-authorize every open connection
        (:func:`fleetctl.server.reauth.reload_auth`).

        Returns:
            ``(kept, closed)``: authenticated connections kept and closed.
        """
        kept_closed = reauth.reload_auth(self, auth)
        firstframes.drop_revoked_latched(self)
        return kept_closed

    def current_identities(self, peer: Peer) -> list[Identity]:
        """*peer*'s identities under the current auth map
        (:func:`fleetctl.server.reauth.current_identities`)."""
        return reauth.current_identities(self, peer)

    def close_peer(self, peer: Peer) -> None:
        """Forget a closed connection; count what its scheduler dropped."""
        if self.peers.pop(peer.peer_id, None) is None:
            return
        self.subs.remove(peer)
        self.keyframes.forget(peer)
        if self.catalog is not None:
            self.catalog.forget(peer)
        if peer.session is not None:
            self._detach_session(peer)
        if peer.standby_key is not None:
            self._unregister_standby(peer)
        for name in peer.robots:
            self.registry.detach(name)
        self.connections.remove(peer.counted)
        peer.counted = ()
        self.metrics.connections_open -= 1

    def close_with(self, peer: Peer, code: int, reason: str) -> None:
        if not peer.closing:
            self.metrics.count_close(code)
            log.warning("%s closed %d: %s", peer.label, code, reason)
        peer.close(code, reason)

    # -- frames ---------------------------------------------------------------------

    def on_binary(self, peer: Peer, frame: bytes, *, hold: bool = False) -> bool:
        """Handle one binary frame from *peer* (Algorithm 3).

        Args:
            hold: The caller keeps a frame this declines, and every later one of the
                connection, in order, and offers it again once :attr:`Peer.throttled` is
                cleared (the I/O layer of a fleetctl connection: back-pressure, see
                :meth:`_allow`). ``False`` (the Foxglove adapter): such a frame is
                dropped, counted.

        Returns:
            ``False`` only with *hold*: the connection is over a rate of its identity
            set, the frame was not taken and is to be offered again.
        """
        if peer.throttled:
            if hold:
                return False
            self.discard(peer)
            return True
        perms = peer.perms
        if perms is None:
            self.close_with(peer, protocol.CLOSE_NO_IDENTITY,
                        "connection matches no identity: send a token frame first")
            return True
        if peer.standby:
            self._standby_frame(peer)
            return True
        try:
            meta, root = read_root(frame)
        except WireError as exc:
            self.malformed(peer, "malformed_frame", None, str(exc))
            return True
        peer.malformed_in_row = 0
        topic = meta.topic
        if topic == SUBSCRIPTION_TOPIC:
            return self._on_subscription(peer, frame, meta.type, hold)
        if topic == KEYFRAME_REQUESTS_TOPIC:  # a control topic: no send rule needed
            firstframes.on_keyframe_request(self, peer, frame, meta.type)
            return True
        if not perms.may_send(topic):
            self._unauthorized(peer, topic)
            return True
        if not self.subs.routes(topic) and not self._new_topic(peer, topic, hold):
            return not hold
        self.metrics.count_in(topic, len(frame))
        message_id: int | None = None
        if meta.type == FRAGMENT_TYPE:
            try:
                message_id = read_fragment_id(frame, root)
            except WireError as exc:
                self.malformed(peer, "malformed_frame", topic, str(exc))
                return True
        elif meta.type == VIDEO_TYPE:
            self.keyframes.note_publisher(topic, peer)
        self._note_robot(peer, topic, meta.type, frame)
        if self.recorder is not None:
            self.recorder.offer(peer.peer_id, perms, topic, frame)
        if self.catalog is not None:
            self.catalog.note(peer, topic, meta.type, frame)
        no_drop = meta.no_drop or self._forced_no_drop(topic)
        self.fanout.publish(topic, frame, no_drop, message_id)
        if no_drop and self.store_acks is not None:
            peer.store_mark = self.store_acks.offered  # this frame's, or an earlier one's
        if meta.latched:
            firstframes.keep_latched(self, peer, topic, frame, root, message_id is not None)
        return True

    def on_remote(self, frame: bytes) -> None:
        """Deliver a frame another replica accepted to local subscribers only (it was
        authorized at its sender's edge; receive rules apply here as for any frame).
        Never published again, so frames do not loop between replicas.

        Raises:
            WireError: The frame does not parse.
        """
        meta, root = read_root(frame)
        topic = meta.topic
        message_id = read_fragment_id(frame, root) if meta.type == FRAGMENT_TYPE else None
        if meta.type == VIDEO_TYPE and topic not in self.remote_video:
            firstframes.on_remote_video_topic(self, topic)
        no_drop = meta.no_drop or self._forced_no_drop(topic)
        self.local.publish(topic, frame, no_drop, message_id)

    def use_fanout(self, fanout: Fanout) -> None:
        """Carry accepted frames with *fanout* (before any connection subscribes)."""
        assert not len(self.subs), "set the fan-out before serving"
        self.fanout = fanout

    def use_shared_sessions(self, shared: SharedSessions) -> None:
        """Keep named sessions in the cluster's shared records and stream."""
        assert not len(self.sessions), "set the shared sessions before serving"
        self.sessions.shared = shared
        self.store_acks = shared.acks

    def _follow(self, pattern: str, receive: tuple[str, ...], delta: int) -> None:
        self.fanout.follow(pattern, delta, receive)

    def on_text(self, peer: Peer, text: str, *, hold: bool = False) -> bool:
        """Handle one text frame: a token frame, a ``list_robots`` request or a standby's
        ``activate``. *hold* and the result: as :meth:`on_binary`'s."""
        if peer.throttled:
            if hold:
                return False
            self.discard(peer)
            return True
        try:
            data: Any = json.loads(text) if len(text) <= protocol.MAX_TEXT_CHARS else None
        except (ValueError, RecursionError):  # RecursionError: "[[[[...": deep nesting
            data = None
        if not isinstance(data, dict):
            self.malformed(peer, "malformed_frame", None, "text frame is not a JSON object")
            return True
        if ("token" in data or data.get("type") == "list_robots") and not self._allow(peer):
            return not hold
        if "token" in data:
            self.on_token(peer, data["token"], data.get("session"))
        elif data.get("type") == "list_robots" and peer.perms is not None:
            peer.malformed_in_row = 0
            peer.outbound.push_control(json.dumps({"type": "robots",
                                                   "robots": self.robots_for(peer.perms)}))
        elif peer.perms is None:
            self.close_with(peer, protocol.CLOSE_NO_IDENTITY, "connection matches no identity")
        elif data.get("type") == "activate":  # once per connection: no control request
            self.activate(peer)
        else:
            self.malformed(peer, "unknown_type", None, "text frames are {'token': ...}, "
                           "{'type': 'list_robots'} or {'type': 'activate'}")
        return True

    def on_token(self, peer: Peer, token: Any, session: Any = None) -> None:
        """Authenticate *peer* by a token; close with 4401 if it matches no identity.

        *session* (the token frame's ``session`` field) names the connection's session;
        it is taken only before the connection has a session or subscriptions (else 4400).
        """
        wait_s = self.logins.retry_after_s(peer.address)
        if wait_s > 0:  # refused before hashing: the address is over its budget
            self.logins.refused()
            message = (f"too many failed logins from this address: retry in "
                       f"{math.ceil(wait_s)} s")
            self.login_refused(peer, protocol.CLOSE_LOGINS_THROTTLED, "login_throttled",
                               message, message, "token refused unhashed")
            return
        identity = self.auth.match_token(token)  # None for anything not a token
        if identity is None:
            self.logins.failed(peer.address)
            self.login_refused(peer, protocol.CLOSE_BAD_TOKEN, "bad_token", "unknown token",
                               "bad token", "failed login (bad token frame)")
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

    def login_refused(self, peer: Peer, close: int, code: str, message: str, reason: str,
                      what: str | None) -> None:
        """Close *peer* for a token that failed (``bad_token``, 4401) or was refused
        unhashed (``login_throttled``, 4429): an error frame (*code*, *message*), the
        close (*close*, *reason*), counted; logged only when
        :meth:`FailedLogins.log_line` says so (not two lines per attempt; *what*
        ``None``: the caller logged it)."""
        self.send_error(peer, code, None, message)
        line = None if what is None else self.logins.log_line(peer.address,
                                                               f"{what} on {peer.label}")
        if line is not None:
            log.warning("%s", line)
        if not peer.closing:
            self.metrics.count_close(close)
        peer.close(close, reason)

    def subscribe(self, peer: Peer, pattern: str, *, charge: bool = True) -> bool:
        """Subscribe an authenticated *peer* to *pattern* as a ``/subscriptions`` frame
        would (control rate, limits, receive rules, latched messages), for adapters of
        other protocols (Foxglove). A refusal is answered with an error frame.

        Args:
            charge: Spend a control request (``False``: the caller spent it, see
                :meth:`allow_control`).

        Returns:
            Whether the subscription is in place.
        """
        return (not charge or self._allow(peer)) and self._subscribe(peer, pattern)

    def allow_control(self, peer: Peer) -> bool:
        """Spend one control request of *peer* (adapters: one per item of a request);
        ``False``: over the rate, the connection is throttled (see :meth:`_allow`) and
        what it sent meanwhile is to be discarded (:meth:`discard`)."""
        return self._allow(peer)

    def unsubscribe(self, peer: Peer, pattern: str) -> None:
        """Drop *peer*'s subscription *pattern* (no answer; unknown patterns are ignored)."""
        self.subs.unsubscribe(peer, pattern)

    def robots_for(self, perms: Permissions | None) -> list[dict[str, Any]]:
        """Robots whose ``/<name>/status`` *perms* may receive (None: every robot), as
        JSON-ready dicts, by name: the registry's, and the auth map's robots it has not
        seen yet (:func:`~fleetctl.server.expectedrobots.never_connected`)."""

        def shown(name: str) -> bool:
            return perms is None or perms.may_receive(f"/{name}/status")

        names = [n for n in self.registry.names() if shown(n)]
        if self._expected[0] is not self.auth:  # reloaded since
            self._expected = (self.auth, expected_robots(self.auth))
        seen = set(names)
        unseen = [never_connected(n) for n in self._expected[1] if n not in seen and shown(n)]
        listed = self.registry.as_json(names)
        return sorted(listed + unseen, key=lambda r: r["name"]) if unseen else listed

    def session_gauges(self) -> list[tuple[str, str, str, dict[str, float]]]:
        """Session gauges for ``/metrics``: sessions by state, mailbox depth per session
        (its mailbox while offline, the part not yet sent once a connection attached)."""
        frames: dict[str, float] = {}
        nbytes: dict[str, float] = {}
        for session in self.sessions:
            peer, label = session.attached, session.metric_id
            if peer is None:
                frames[label] = float(len(session.mailbox))
                nbytes[label] = float(session.mailbox.nbytes)
            else:
                frames[label] = float(peer.outbound.backlog_frames)
                nbytes[label] = float(peer.outbound.backlog_bytes)
        offline = self.sessions.offline_count
        return [
            ("fleetctl_sessions", "Named sessions by state.", "state",
             {"online": float(len(self.sessions) - offline), "offline": float(offline)}),
            ("fleetctl_session_mailbox_frames", "no_drop frames held for a session.",
             "session", frames),
            ("fleetctl_session_mailbox_bytes", "Bytes held for a session.", "session", nbytes),
        ]

    # -- standby connections ------------------------------------------------------------

    def activate(self, peer: Peer) -> None:
        """``{"type": "activate"}`` from an authenticated *peer*: a standby becomes the
        robot's connection (``welcome`` again, then its session is attached, taking it
        over from the robot's current connection: 4409). Anything but a standby gets a
        ``not_standby`` error and stays open."""
        if not peer.standby:
            self.malformed(peer, "not_standby", None, "activate: this connection is not a "
                           "standby (X-Fleetctl-Standby: 1 on the upgrade)")
            return
        name = peer.session_name
        assert peer.perms is not None and name is not None
        self._unregister_standby(peer)
        peer.standby = False
        peer.malformed_in_row = 0
        if peer.on_activated is not None:
            peer.on_activated()
        peer.outbound.push_control(protocol.welcome(peer.perms))
        log.info("%s activated its standby for session %s", peer.label, name)
        self._attach_session(peer, name)

    def register_standby(self, peer: Peer) -> None:
        """Keep an authenticated standby *peer* as the one standby of its session key (on
        authentication, and again when an auth map reload changed its identities); an
        older standby of the key is closed with 4409. A bad session name closes *peer*
        with 4400, as :meth:`_attach_session` would."""
        assert peer.standby and peer.session_name is not None
        try:
            check_session_name(peer.session_name)
        except BadSessionName as exc:
            self._bad_session(peer, str(exc))
            return
        key = _session_key(peer, peer.session_name)
        if peer.standby_key == key:
            return
        self._unregister_standby(peer)
        old = self.standbys.get(key)
        if old is not None:
            old.standby_key = None
            self.close_with(old, protocol.CLOSE_SESSION_TAKEN_OVER,
                            "standby replaced by a newer one")
        self.standbys[key] = peer
        peer.standby_key = key
        log.info("%s is a standby for session %s", peer.label, session_label(key))

    def _unregister_standby(self, peer: Peer) -> None:
        key, peer.standby_key = peer.standby_key, None
        if key is not None and self.standbys.get(key) is peer:
            del self.standbys[key]

    def _standby_frame(self, peer: Peer) -> None:
        """A binary frame of a standby: discarded, counted; the first one is answered
        (and logged), like a refused send (:meth:`_unauthorized`)."""
        self.metrics.count_error("standby")
        if peer.standby_warned:
            return
        peer.standby_warned = True
        log.warning("%s sent a binary frame on its standby connection", peer.label)
        peer.outbound.push_control(protocol.error(
            "standby", None, "a standby connection relays nothing: send "
            "{'type': 'activate'} first (frames are discarded)"))

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
        key = _session_key(peer, name)
        existing = self.sessions.get(key)
        if existing is not None and existing.patterns and self._resume_in_debt(peer):
            return
        if existing is not None and existing.attached is not None:
            old = existing.attached
            log.warning("%s takes session %s over from %s", peer.label, existing.label,
                        old.label)
            self.subs.remove(old)
            self._detach_session(old)
            self.close_with(old, protocol.CLOSE_SESSION_TAKEN_OVER,
                        "session taken over by a newer connection")
        session = self.sessions.attach(key, peer.perms, peer)
        if session is None:
            self._bad_session(peer, f"identity holds {self.limits.max_sessions_per_identity}"
                                    " sessions already")
            return
        resumed = session.resumed
        peer.session = session
        backlog = session.mailbox.take()
        patterns = list(session.patterns)
        peer.outbound.track_acks()
        if self.sessions.shared is not None:
            self._feed_from_stream(peer, session)
        peer.outbound.push_control(protocol.session(name, resumed, len(backlog), patterns))
        peer.outbound.push_backlog(backlog)
        held = set(self.subs.patterns(peer))
        for pattern in patterns:  # the client's own resubscribe is then a no-op
            if self._subscribe(peer, pattern, first_frames=False):
                peer.outbound.push_control(protocol.ack("subscribed", pattern))
            else:
                self.sessions.forget_pattern(session, pattern)
        # Their first frames together: each store looked at once, not once per pattern.
        self._first_frames(peer, [p for p in self.subs.patterns(peer) if p not in held])
        if resumed:
            log.info("%s resumed session %s (metrics: %s): %d mailbox frames, %d "
                     "subscriptions (%d frames dropped in total)", peer.label, session.label,
                     session.metric_id, len(backlog), len(patterns), session.dropped)
        else:
            log.info("%s opened session %s (metrics: %s)", peer.label, session.label,
                     session.metric_id)

    def _detach_session(self, peer: Peer) -> None:
        """*peer* leaves its session: what it may not have delivered goes to the mailbox
        (in a cluster: stays in the stream, after the session's cursor)."""
        session, peer.session = peer.session, None
        assert session is not None
        shared = self.sessions.shared
        if shared is None:
            self.sessions.detach(session, peer.outbound.take_no_drop())
            return
        peer.stream_feed = None
        shared.detach(session.key, ended=not session.patterns)  # reads the acks first
        peer.outbound.take_no_drop()
        self.sessions.detach(session, ())

    def _feed_from_stream(self, peer: Peer, session: Session[Peer]) -> None:
        """In a cluster the session's no_drop frames come from the shared stream."""
        assert self.sessions.shared is not None

        def wants(topic: str) -> bool:
            return peer in self.subs.receivers(topic)

        def is_open() -> bool:
            return peer.session is session and not peer.closing

        def taken() -> None:  # another replica's connection attached to it: newer
            if peer.session is not session:
                return
            self.subs.remove(peer)
            self._detach_session(peer)
            self.close_with(peer, protocol.CLOSE_SESSION_TAKEN_OVER,
                            "session taken over by a newer connection (another replica)")

        peer.stream_feed = self.sessions.shared.attach(
            session.key, session.patterns, peer.outbound, wants, is_open, taken)

    def _bad_session(self, peer: Peer, message: str) -> None:
        self.send_error(peer, "bad_session", None, message)
        self.close_with(peer, protocol.CLOSE_BAD_SESSION, message[:120])

    # -- helpers ----------------------------------------------------------------------

    def send_error(self, peer: Peer, code: str, topic: str | None, message: str) -> None:
        self.metrics.count_error(code)
        peer.outbound.push_control(protocol.error(code, topic, message))

    def malformed(self, peer: Peer, code: str, topic: str | None, message: str) -> None:
        self.send_error(peer, code, topic, message)
        peer.malformed_in_row += 1
        if peer.malformed_in_row >= self.limits.max_malformed_in_row:
            self.close_with(peer, protocol.CLOSE_MALFORMED,
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
                self.send_error(peer, "malformed_frame", topic, "RobofleetStatus does not decode")
            else:
                self.registry.set_status(name, *status)

    def _allow(self, peer: Peer) -> bool:
        """Spend one control request of *peer*'s identity set. Free before the connection
        has an identity (its first token frame).

        An empty bucket throttles the connection (:meth:`_throttle`): one
        ``rate_limited`` error frame, and the I/O layer stops reading from it until the
        bucket has a token again. A fleetctl connection's I/O layer keeps the request and
        everything read after it (``hold``, :meth:`on_binary`) and offers them again
        then, in order: nothing is lost, so no pong says that a dropped frame was taken
        (docs/security.md), and TCP pushes back on the client meanwhile. A flooding
        client still costs the relay one socket read per pause and one refused request,
        not work per frame. (The Foxglove adapter's requests are dropped instead, and
        what the connection sends meanwhile is discarded, counted: :meth:`discard`.)
        """
        if peer.perms is None:
            return True
        bucket = self._control_bucket(peer)
        if bucket.take():
            return True
        self.send_error(peer, "rate_limited", None, "more than "
                        f"{self.limits.max_control_requests_per_s:g} control requests/s "
                        "(subscribe, unsubscribe, token, list_robots): this connection is "
                        "not read for a moment")
        self._throttle(peer, "control_rate", bucket)
        return False

    def _throttle(self, peer: Peer, reason: str, bucket: TokenBucket) -> None:
        """Stop reading from *peer* until *bucket* has a token (the I/O layer clears
        :attr:`Peer.throttled` then); counted in ``fleetctl_reads_paused_total``."""
        peer.throttled = True
        self.metrics.count_read_paused(reason)
        if peer.throttle is not None:
            peer.throttle(bucket.wait_s())

    def _control_bucket(self, peer: Peer) -> TokenBucket:
        """The control requests left to *peer*'s identity set (made on first use)."""
        key = peer.identity_names
        bucket = self._buckets.get(key)
        if bucket is None:
            limits = self.limits
            burst = max(limits.max_subscriptions_per_connection, MIN_CONTROL_BURST)
            bucket = self._buckets[key] = TokenBucket(
                limits.max_control_requests_per_s, burst, self._clock)
        return bucket

    def _new_topic(self, peer: Peer, topic: str, hold: bool) -> bool:
        """Spend one of *peer*'s identity set's new-topic tokens (:data:`NEW_TOPICS_PER_S`).

        ``False``: none left. With *hold* (a fleetctl connection) the connection is
        throttled as over the control rate (:meth:`_allow`): the frame and what follows
        it wait, unread, until a token is there, then are taken in order. Without (the
        Foxglove adapter's client publishing) the frame is dropped, counted as
        ``new_topic_rate``. The first time per connection: one error frame and one log
        line."""
        key = peer.identity_names
        bucket = self._topic_buckets.get(key)
        if bucket is None:
            bucket = self._topic_buckets[key] = TokenBucket(NEW_TOPICS_PER_S, NEW_TOPICS_BURST,
                                                            self._clock)
        if bucket.take():
            return True
        if hold:
            self._throttle(peer, "new_topic_rate", bucket)
        else:
            self.metrics.count_error("new_topic_rate")
        if not peer.new_topics_refused:
            peer.new_topics_refused = True
            what = "wait, unread," if hold else "are dropped"
            log.warning("%s: more than %g new topics/s (bursts of %d): frames on topics not "
                        "routed yet %s meanwhile", peer.label, NEW_TOPICS_PER_S,
                        NEW_TOPICS_BURST, what)
            peer.outbound.push_control(protocol.error(
                "rate_limited", topic, f"more than {NEW_TOPICS_PER_S:g} new topics/s: frames "
                f"on topics the server has not routed yet {what} for a moment"))
        return False

    def discard(self, peer: Peer) -> None:
        """Count one frame of a throttled *peer* whose caller does not hold frames (the
        Foxglove adapter), discarded unread."""
        self.metrics.count_error("rate_limited")

    def _count_refusal(self, peer: Peer) -> None:
        peer.over_limit_subscriptions += 1
        if peer.over_limit_subscriptions > self.limits.max_subscriptions_per_connection:
            self.close_with(peer, protocol.CLOSE_SUBSCRIPTION_FLOOD,
                            "subscription flood past the limit")

    def _on_subscription(self, peer: Peer, frame: bytes, type_name: str, hold: bool) -> bool:
        """Handle one ``/subscriptions`` frame; ``False``: as :meth:`on_binary`'s."""
        # Sending on /subscriptions needs no rule (docs/design.md section 3).
        if not self._allow(peer):
            return not hold
        if type_name != SUBSCRIPTION_TYPE:
            self.malformed(peer, "unknown_type", SUBSCRIPTION_TOPIC,
                           f"/subscriptions carries RobofleetSubscription, not {type_name}")
            return True
        fields = protocol.decode_subscription_fields(frame)
        if fields is None:
            self.malformed(peer, "malformed_frame", SUBSCRIPTION_TOPIC,
                           "RobofleetSubscription does not decode")
            return True
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
        return True

    def _subscribe(self, peer: Peer, pattern: str, *, first_frames: bool = True) -> bool:
        assert peer.perms is not None
        try:
            added = self.subs.subscribe(peer, peer.perms, pattern, peer.identity_names)
        except Refusal as refusal:
            self.send_error(peer, refusal.code, pattern[:200], refusal.message)
            if refusal.code == "too_many_subscriptions":
                self._count_refusal(peer)
            return False
        if added and first_frames:  # a repeat (a client's resubscribe) gets nothing
            self._first_frames(peer, [pattern])
        return True

    def _resume_in_debt(self, peer: Peer) -> bool:
        """Refuse a session resume while *peer*'s identity set still owes control
        requests for earlier first frames (its bucket below empty, :meth:`_first_frames`):
        an error frame, then close 4429 with the wait; the session stays for a later
        attach. Why: reconnecting is not a control request, and a resume matches every
        pattern of the session against the stores again, so a token holding 200
        patterns RE2 cannot bound beside full stores cost ~0.3 s of the loop per
        reconnect, however fast it reconnected. A bucket that is only empty (a burst of
        plain subscribes) is not refused: only work the relay already did and was not
        yet paid for."""
        bucket = self._control_bucket(peer)
        owed = -bucket.level()
        if owed <= 0:
            return False
        wait_s = math.ceil(owed / bucket.rate_per_s) if bucket.rate_per_s > 0 else 1
        message = (f"session resumes over the control request rate (the last ones' first "
                   f"frames are not paid for yet): retry in {wait_s} s")
        self.send_error(peer, "resume_throttled", None, message)
        self.close_with(peer, protocol.CLOSE_SUBSCRIPTION_FLOOD, message)
        return True

    def _first_frames(self, peer: Peer, patterns: list[str]) -> None:
        """Queue what *patterns*, just added, start delivering first; charge the work."""
        started = self._clock()
        work = firstframes.on_new_subscriptions(self, peer, patterns)
        extra = firstframes.extra_requests(work, self._clock() - started)
        if extra:  # work done: served, and the next control requests wait for it
            self._control_bucket(peer).charge(extra)


def _session_key(peer: Peer, name: str) -> SessionKey:
    """The key of *peer*'s session *name*: its sorted identity names and the name."""
    return tuple(sorted(i.name for i in peer.identities)), name


def _session_store(registry: RobotRegistry) -> SessionStore | None:
    try:
        return SessionStore(registry.db)
    except sqlite3.Error:  # sessions then live in memory only; the relay still runs
        log.exception("cannot open the sessions table: sessions will not survive a restart")
        return None

