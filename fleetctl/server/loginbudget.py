"""Failed logins per client address, bounded (docs/security.md, "Failed logins").

Tokens are 256-bit: guessing one is hopeless. What a stream of wrong tokens costs is the
server's work and its log: a SHA-256 and a lookup, a connection and its close, and two
log lines per attempt. So each client address (an IPv4 address, an IPv6 /64:
:func:`~fleetctl.server.addressgroup.address_group`) may fail :data:`FAILURES_BURST`
times at once and then once per :data:`FAILURE_INTERVAL_S` (a token bucket); while it is
over that budget, every token it presents is refused before it is hashed (HTTP 429 at
the upgrade, close 4429 for a token frame). Connections that present no token (robots by
their WireGuard address, the operator on loopback) are never refused, and other
addresses are never affected. The host's own loopback address (``127.0.0.1``, ``::1``)
has no budget: it is the operator on the server host, or a reverse proxy on it that is
not in ``trusted_proxies``, behind which one client's failures would lock every user out
(the server warns about such a proxy, docs/security.md).

Pure bookkeeping with an injected clock; the relay and the asyncio layer ask and act.
Bounded: at most :data:`MAX_ADDRESSES` addresses are remembered, the least recently
failing forgotten first (counted in :attr:`FailedLogins.evicted` when it still held
failures). Failures and refusals are logged at most once per :data:`LOG_INTERVAL_S`
(:meth:`FailedLogins.log_line`), with the counts since the last line.
"""

from __future__ import annotations

import ipaddress
import math
import time
from collections.abc import Callable

from fleetctl.server.addressgroup import address_group
from fleetctl.server.admission import TokenBucket
from fleetctl.server.identity import parse_address

# Why these: an operator's page or CLI with a stale token retries with backoff and stays
# within 20 at once and one every 2 s; a script trying tokens flat out is refused
# unhashed after its first 20 (and keeps its rate at 0.5 tries/s).
FAILURES_BURST = 20
FAILURE_INTERVAL_S = 2.0
# Why a bound: addresses are the attacker's to choose (an IPv6 /48 holds 65,536 /64s);
# ~150 bytes an entry, ~0.6 MB at most.
MAX_ADDRESSES = 4096
LOG_INTERVAL_S = 10.0
# Addresses without a budget (see above); an IPv4-mapped ::ffff:127.0.0.1 is 127.0.0.1.
UNLIMITED = frozenset({ipaddress.ip_address("127.0.0.1"), ipaddress.ip_address("::1")})


class FailedLogins:
    """A failure budget per client address.

    Args:
        burst: Failures an address may have at once (default :data:`FAILURES_BURST`).
        interval_s: Seconds after which it may fail once more (default
            :data:`FAILURE_INTERVAL_S`).
        max_addresses: Addresses remembered (default :data:`MAX_ADDRESSES`).
        clock: Monotonic clock in seconds.

    Attributes:
        failures: Failed logins recorded.
        refusals: Tokens refused unhashed (address over its budget).
        evicted: Addresses forgotten, to stay within *max_addresses*, while they still
            held failures.
    """

    def __init__(self, burst: int | None = None, interval_s: float | None = None,
                 max_addresses: int | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.burst = float(FAILURES_BURST if burst is None else burst)
        self.interval_s = FAILURE_INTERVAL_S if interval_s is None else interval_s
        self.max_addresses = MAX_ADDRESSES if max_addresses is None else max_addresses
        self._clock = clock
        # address group -> what it may still fail, least recently failing first
        self._table: dict[str, TokenBucket] = {}
        self.failures = 0
        self.refusals = 0
        self.evicted = 0
        self._logged_at_s = -math.inf
        self._since_log = [0, 0]  # failures, refusals since the last log line

    def __len__(self) -> int:
        return len(self._table)

    def retry_after_s(self, address: str | None) -> float:
        """Seconds until *address* may present a token again; 0: it may now (``None``,
        an unknown address, always may)."""
        if _unlimited(address):
            return 0.0
        assert address is not None
        budget = self._table.get(address_group(address))
        if budget is None or budget.level() >= 1.0:
            return 0.0
        return budget.wait_s()

    def refused(self) -> None:
        """Count one token refused unhashed (its address was over its budget)."""
        self.refusals += 1
        self._since_log[1] += 1

    def failed(self, address: str | None) -> None:
        """Record one failed login (a token that matches no identity) from *address*."""
        self.failures += 1
        self._since_log[0] += 1
        if _unlimited(address):
            return
        assert address is not None
        key = address_group(address)
        budget = self._table.pop(key, None)  # re-inserted last: least recent stays first
        if budget is None:
            budget = TokenBucket(1.0 / self.interval_s, self.burst, self._clock)
            self._make_room()
        budget.spend()
        self._table[key] = budget

    def log_line(self, address: str | None, what: str) -> str | None:
        """The log line for a failure or refusal just counted, or ``None`` when one was
        logged less than :data:`LOG_INTERVAL_S` ago (the next one carries the counts)."""
        now = self._clock()
        if now - self._logged_at_s < LOG_INTERVAL_S:
            return None
        first = self._logged_at_s == -math.inf
        self._logged_at_s = now
        failures, refusals = self._since_log
        self._since_log = [0, 0]
        where = address_group(address) if address is not None else "an unknown address"
        if first:
            return (f"{what} from {where} (failed logins are logged at most once per "
                    f"{LOG_INTERVAL_S:g} s: fleetctl_errors_total{{code=\"bad_token\"}} and "
                    "{code=\"login_throttled\"} count them all)")
        return (f"{what} from {where}; since the last such line: {failures} failed "
                f"logins, {refusals} tokens refused unhashed ({self._over()} addresses "
                "over their budget)")

    def _make_room(self) -> None:
        while len(self._table) >= self.max_addresses:
            oldest = next(iter(self._table))
            if self._table.pop(oldest).level() < self.burst:
                self.evicted += 1  # it still held failures: its budget is lost

    def _over(self) -> int:
        return sum(1 for b in self._table.values() if b.level() < 1.0)


def _unlimited(address: str | None) -> bool:
    """Whether *address* has no budget: unknown (``None``), or this host's loopback."""
    return address is None or parse_address(address) in UNLIMITED
