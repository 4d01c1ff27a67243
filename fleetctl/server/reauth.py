"""Applying a reloaded auth map to a running :class:`~fleetctl.server.relay.RelayCore`:
every open connection is re-authorized (docs/server.md, "Reloading the auth map")."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from fleetctl.server import protocol
from fleetctl.server.authmap import AuthMap, Identity
from fleetctl.server.identity import parse_address
from fleetctl.server.permissions import PermissionsPool

if TYPE_CHECKING:
    from fleetctl.server.peer import Peer
    from fleetctl.server.relay import RelayCore

log = logging.getLogger("fleetctl.server")


def reload_auth(core: RelayCore, auth: AuthMap) -> tuple[int, int]:
    """Switch *core* to a reloaded auth map and re-authorize every open connection.

    Each authenticated connection's identities are recomputed from its address
    (address identities) and its token digests. A connection left with none is closed
    with 4403 and stops receiving at once; the others keep their connection, get the
    new permissions (a new ``welcome`` if its rules changed; a standby connection gets
    it when it activates) and lose the
    subscriptions they may no longer hold (an ``error`` and an ``unsubscribed`` frame
    each). Permission caches and receiver caches are rebuilt; sessions follow
    (:meth:`SessionTable.reauthorize`).

    Returns:
        ``(kept, closed)``: authenticated connections kept and closed.
    """
    core.auth = auth
    core.pool = PermissionsPool()  # the old one caches answers of the old rules
    core.sessions.reauthorize(auth, core.pool)
    kept = closed = 0
    for peer in list(core.peers.values()):
        if peer.perms is None or peer.closing:
            continue  # not authenticated yet: it will be, against the new map
        identities = current_identities(core, peer)
        if identities:
            regrant(core, peer, identities)
            kept += 1
        else:
            core.subs.remove(peer)  # nothing more is queued for it from now on
            core.close_with(peer, protocol.CLOSE_NO_IDENTITY,
                            "credentials revoked (auth map reloaded)")
            closed += 1
    return kept, closed


def current_identities(core: RelayCore, peer: Peer) -> list[Identity]:
    """*peer*'s identities under *core*'s current auth map: address ones (if they apply
    to it) and those of its token digests, deduplicated by name."""
    found: dict[str, Identity] = {}
    if peer.by_address:
        for ident in core.auth.match_address(parse_address(peer.address)):
            found.setdefault(ident.name, ident)
    for digest in sorted(peer.token_digests):
        by_token = core.auth.match_digest(digest)
        if by_token is not None:
            found.setdefault(by_token.name, by_token)
    return list(found.values())


def regrant(core: RelayCore, peer: Peer, identities: list[Identity]) -> None:
    """Give a still-allowed *peer* the permissions of its recomputed *identities*."""
    assert peer.perms is not None
    before = protocol.welcome(peer.perms)
    peer.identities = identities
    peer.perms = core.pool.get(identities)
    peer.is_robot = any(i.by_address for i in identities)
    peer.refused_topics.clear()  # a refused send may be allowed now, and the reverse
    core.recount(peer)
    welcome = protocol.welcome(peer.perms)
    if peer.standby:  # sent nothing while standby: activating welcomes it anew
        core.register_standby(peer)  # its session key may have changed
    elif welcome != before:
        peer.outbound.push_control(welcome)
        log.info("%s re-authorized: rules changed", peer.label)
    for pattern, refusal in core.subs.set_permissions(peer, peer.perms):
        core.send_error(peer, refusal.code, pattern, f"{refusal.message} (auth map reloaded)")
        peer.outbound.push_control(protocol.ack("unsubscribed", pattern))
        if peer.session is not None:
            core.sessions.forget_pattern(peer.session, pattern)
