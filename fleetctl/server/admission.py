"""Who may take how much of the relay: rate limits and connection caps (docs/security.md).

Pure bookkeeping, no I/O, injected clocks; the relay and the asyncio layer ask and act
(refuse a request, abort a socket, close a connection).

- :class:`TokenBucket`: control requests of one connection (subscribe/unsubscribe, token
  frames, ``list_robots``); each costs the relay work outside its hot path.
- :class:`UnauthenticatedGate`: connections that have no identity yet (from accept to
  authentication), server-wide and per source address (an IPv6 /64 counts as one
  address, :func:`~fleetctl.server.addressgroup.address_group`): before authentication the
  server cannot tell a robot from an attacker, so each such connection gets a small frame
  bound and a slot under these caps.
- :class:`IdentityConnections`: authenticated connections per identity name.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable

from fleetctl.server.addressgroup import address_group


class TokenBucket:
    """A token bucket: *burst* requests at once, *rate_per_s* sustained.

    Args:
        rate_per_s: Tokens added per second.
        burst: Bucket size (and the initial fill).
        clock: Monotonic clock in seconds.
    """

    __slots__ = ("_clock", "_last_s", "_tokens", "burst", "rate_per_s")

    def __init__(self, rate_per_s: float, burst: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.rate_per_s = rate_per_s
        self.burst = burst
        self._clock = clock
        self._tokens = burst
        self._last_s = clock()

    def level(self) -> float:
        """The tokens in the bucket now (refilled up to *burst*)."""
        now = self._clock()
        self._tokens = min(self.burst, self._tokens + (now - self._last_s) * self.rate_per_s)
        self._last_s = now
        return self._tokens

    def spend(self) -> None:
        """Spend one token, or what is left when less than one is: for a cost that was
        incurred anyway (a failed login), which must not be refused."""
        self._tokens = max(0.0, self.level() - 1.0)

    def charge(self, tokens: float) -> None:
        """Spend *tokens* at once, going below empty (down to ``-burst``) when fewer are
        there: for work already done whose size was known only then (a subscription's
        first frames); :meth:`take` then fails until the refill has paid it back."""
        self._tokens = max(-self.burst, self.level() - tokens)

    def take(self) -> bool:
        """Spend one token; return ``False`` (nothing spent) when the bucket is empty."""
        if self.level() < 1.0:
            return False
        self._tokens -= 1.0
        return True

    def wait_s(self) -> float:
        """Seconds until the next token (0 when one is there)."""
        return max(0.0, (1.0 - self._tokens) / self.rate_per_s) if self.rate_per_s > 0 else 1.0


class UnauthenticatedGate:
    """Slots for connections without an identity yet.

    Args:
        max_total: Slots server-wide.
        max_per_address: Slots per source address, counted by *group*.
        exempt: Whether an address has no per-address cap (a trusted proxy); its
            connections count only toward *max_total*.
        refused: Where refusals are counted by cap (e.g. the server's metrics).
        group: The key an address is counted under (default: an IPv6 /64 is one
            address, an IPv4-mapped IPv6 address its IPv4 address).
    """

    def __init__(self, max_total: int, max_per_address: int,
                 exempt: Callable[[str], bool] = lambda _a: False,
                 refused: dict[str, int] | None = None,
                 group: Callable[[str], str] = address_group) -> None:
        self.max_total = max_total
        self.max_per_address = max_per_address
        self._exempt = exempt
        self._group = group
        self._by_address: dict[str, int] = {}
        self.open = 0
        self.refused = refused if refused is not None else {}
        self.refused.setdefault("total", 0)
        self.refused.setdefault("per_address", 0)

    def admit(self, address: str) -> str | None:
        """Take a slot for a connection from *address*.

        Returns:
            ``None`` when admitted (call :meth:`release` exactly once later), else the
            cap that refused it: ``"total"`` or ``"per_address"`` (counted in
            :attr:`refused`).
        """
        reason: str | None = None
        key = None if self._exempt(address) else self._group(address)
        if self.open >= self.max_total:
            reason = "total"
        elif key is not None and self._by_address.get(key, 0) >= self.max_per_address:
            reason = "per_address"
        if reason is not None:
            self.refused[reason] += 1
            return reason
        self.open += 1
        if key is not None:
            self._by_address[key] = self._by_address.get(key, 0) + 1
        return None

    def release(self, address: str) -> None:
        """Give back the slot of a connection from *address* that authenticated or closed."""
        self.open -= 1
        if self._exempt(address):
            return
        key = self._group(address)
        left = self._by_address.get(key, 0) - 1
        if left > 0:
            self._by_address[key] = left
        else:
            self._by_address.pop(key, None)

    def held(self, address: str) -> int:
        """Slots held now by *address*'s group (0 for an exempt address)."""
        return 0 if self._exempt(address) else self._by_address.get(self._group(address), 0)


class IdentityConnections:
    """Authenticated connections per identity name, capped.

    Args:
        max_per_identity: Connections one identity name may have open.
    """

    def __init__(self, max_per_identity: int) -> None:
        self.max_per_identity = max_per_identity
        self._open: dict[str, int] = {}

    def full(self, names: Iterable[str]) -> str | None:
        """The first of *names* already at its cap, or ``None``."""
        return next((n for n in names if self._open.get(n, 0) >= self.max_per_identity),
                    None)

    def add(self, names: Iterable[str]) -> None:
        """Count one more connection for each of *names*."""
        for name in names:
            self._open[name] = self._open.get(name, 0) + 1

    def remove(self, names: Iterable[str]) -> None:
        """Count one connection less for each of *names*."""
        for name in names:
            left = self._open.get(name, 0) - 1
            if left > 0:
                self._open[name] = left
            else:
                self._open.pop(name, None)

    def count(self, name: str) -> int:
        """Open connections of *name*."""
        return self._open.get(name, 0)
