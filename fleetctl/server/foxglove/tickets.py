"""Short-lived, single-use sign-in tickets for Foxglove viewers.

A browser cannot set headers on a WebSocket, so a Foxglove tab cannot send ``Authorization:
Bearer``; a long-lived token in the URL would end up in browser history, proxy logs and
screenshots. Instead a signed-in caller (Bearer token, over TLS) asks for a ticket and
the tab connects with ``?ticket=...``: the ticket works once, within
:attr:`TicketBook.ttl_s`, and maps to the identity that asked for it.

Only the SHA-256 of a ticket is stored (a memory dump or a repr shows no usable ticket).
The book is bounded: at most ``max_tickets`` outstanding in all, ``max_per_identity`` per
identity (a new one evicts that identity's oldest, so one caller cannot starve others).
"""

from __future__ import annotations

import hashlib
import secrets
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from fleetctl.server.authmap import Identity

DEFAULT_TTL_S = 60.0
DEFAULT_MAX_TICKETS = 1024
DEFAULT_MAX_PER_IDENTITY = 16
_TICKET_BYTES = 32  # 256 bits of randomness, URL-safe base64


class TicketBookFull(Exception):
    """No room for another ticket (``max_tickets`` outstanding and none expired)."""


@dataclass(frozen=True)
class _Entry:
    identity: Identity
    expires_s: float


class TicketBook:
    """Outstanding tickets.

    Args:
        ttl_s: Lifetime of a ticket, seconds.
        max_tickets: Tickets outstanding at once, all identities.
        max_per_identity: Tickets outstanding at once per identity name.
        clock: Monotonic clock, seconds.
    """

    def __init__(self, ttl_s: float = DEFAULT_TTL_S, max_tickets: int = DEFAULT_MAX_TICKETS,
                 max_per_identity: int = DEFAULT_MAX_PER_IDENTITY,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.ttl_s = ttl_s
        self.max_tickets = max_tickets
        self.max_per_identity = max_per_identity
        self._clock = clock
        self._entries: OrderedDict[str, _Entry] = OrderedDict()  # digest -> entry, oldest first
        self.issued = 0
        self.redeemed = 0
        self.refused = 0

    def __len__(self) -> int:
        return len(self._entries)

    def __repr__(self) -> str:
        return f"TicketBook({len(self._entries)} outstanding)"

    def issue(self, identity: Identity) -> str:
        """Return a new ticket for *identity*, valid once within :attr:`ttl_s`.

        Raises:
            TicketBookFull: ``max_tickets`` unexpired tickets are outstanding.
        """
        self._expire()
        mine = [d for d, e in self._entries.items() if e.identity.name == identity.name]
        for digest in mine[: max(0, len(mine) - self.max_per_identity + 1)]:
            del self._entries[digest]
        if len(self._entries) >= self.max_tickets:
            raise TicketBookFull(f"{self.max_tickets} tickets outstanding; try again in "
                                 f"{self.ttl_s:.0f} s")
        ticket = secrets.token_urlsafe(_TICKET_BYTES)
        self._entries[_digest(ticket)] = _Entry(identity, self._clock() + self.ttl_s)
        self.issued += 1
        return ticket

    def redeem(self, ticket: str, accept: bool = True) -> Identity | None:
        """Use *ticket*: its identity, or ``None`` if it is unknown, used or expired.

        With *accept* ``False`` the ticket is burnt and counted refused whatever it was
        (it was presented where it must not be: over plain ``ws://``).
        """
        entry = self._entries.pop(_digest(ticket), None)
        if not accept or entry is None or entry.expires_s <= self._clock():
            self.refused += 1
            return None
        self.redeemed += 1
        return entry.identity

    def _expire(self) -> None:
        now = self._clock()
        while self._entries:
            digest, entry = next(iter(self._entries.items()))
            if entry.expires_s > now:  # same ttl for all: insertion order is expiry order
                break
            del self._entries[digest]


def _digest(ticket: str) -> str:
    return hashlib.sha256(ticket.encode("utf-8", "surrogateescape")).hexdigest()
