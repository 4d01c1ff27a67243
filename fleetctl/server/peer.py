"""One connection as the relay core sees it (:class:`Peer`): its identity, permissions,
outbound scheduler and the per-connection bookkeeping of :mod:`fleetctl.server.relay`."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from fleetctl.server.authmap import Identity
from fleetctl.server.outbound import OutboundScheduler
from fleetctl.server.permissions import Permissions
from fleetctl.server.sessions import Session, SessionKey

if TYPE_CHECKING:
    from fleetctl.server.cluster.sessionfeed import SessionFeed


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
        standby: The upgrade said ``X-Fleetctl-Standby: 1`` (see :attr:`standby`).

    Attributes:
        token_digests: SHA-256 hex digests of the tokens the connection authenticated
            with (never the tokens): what an auth map reload re-checks it by.
        counted: Identity names this connection is counted under (the per-identity
            connection cap).
        on_authenticated: Called once, when the connection first gets an identity (the
            I/O layer lifts its pre-authentication bounds).
        throttle: Asks the I/O layer to stop reading from the connection for a number of
            seconds, then to clear :attr:`throttled` (``None``: the core only discards).
        throttled: The connection is over a rate of its identity set (control requests,
            new topics): its frames wait, unread, until the I/O layer clears this
            (``RelayCore.on_binary``'s *hold*; the Foxglove adapter discards them,
            counted).
        standby: A robot's idle standby connection of :attr:`session_name`: welcomed but
            not attached to the session, sent nothing else, and every binary frame it
            sends is discarded (counted), until ``{"type": "activate"}`` clears this
            (:meth:`~fleetctl.server.relay.RelayCore.activate`).
        standby_key: The session key this standby is registered under in
            ``RelayCore.standbys`` (``None``: not registered).
        standby_warned: A binary frame of this standby was answered with an error already
            (the next ones are only counted).
        on_activated: Called when a standby activates (the I/O layer starts the
            keepalive pings it held back: a ping the server sent into a cut would make
            everything after it on the activated connection wait for TCP's
            retransmission).
    """

    def __init__(
        self,
        peer_id: int,
        address: str | None,
        outbound: OutboundScheduler,
        close: Callable[[int, str], None],
        session_name: str | None = None,
        by_address: bool = True,
        standby: bool = False,
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
        self.counted: tuple[str, ...] = ()
        self.on_authenticated: Callable[[], None] | None = None
        self.on_activated: Callable[[], None] | None = None
        self.throttle: Callable[[float], None] | None = None
        self.throttled = False
        self.standby = standby
        self.standby_key: SessionKey | None = None
        self.standby_warned = False
        self.is_robot = False
        self.closing = False
        # In a cluster, a session's connection: its no_drop frames come from the shared
        # stream through this feed, not from the fan-out (unless the stream is away).
        self.stream_feed: SessionFeed | None = None
        # In a cluster, the number of the last no_drop frame this connection sent into
        # the sessions' stream: its next pong waits until that one is stored
        # (fleetctl.server.heldpongs).
        self.store_mark = 0
        self.malformed_in_row = 0
        self.over_limit_subscriptions = 0
        self.new_topics_refused = False  # told once (RelayCore._new_topic)
        self.robots: set[str] = set()
        self.topic_robot: dict[str, str | None] = {}
        self.refused_topics: set[str] = set()
        self.refused_keyframes: set[str] = set()  # keyframe requests answered with an error

    @property
    def label(self) -> str:
        """Short text naming the connection in log lines (identities and address)."""
        names = ",".join(i.name for i in self.identities) or "-"
        return f"conn#{self.peer_id}[{names}@{self.address}]"

    @property
    def metric_label(self) -> str:
        """The connection in metric labels: opaque (``conn#12``); the log line of its
        authentication says who it is."""
        return f"conn#{self.peer_id}"

    @property
    def identity_names(self) -> tuple[str, ...]:
        """Names of the connection's identities, in the order it got them."""
        return tuple(i.name for i in self.identities)

    def close(self, code: int, reason: str) -> None:
        """Ask the I/O layer to close this connection (once)."""
        if not self.closing:
            self.closing = True
            self._close(code, reason)
