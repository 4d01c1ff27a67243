"""The failed-login budget alone (fleetctl.server.loginbudget), with an injected clock."""

from __future__ import annotations

from fleetctl.server.loginbudget import LOG_INTERVAL_S, FailedLogins
from tests.support import ManualClock


def test_burst_then_one_failure_per_interval() -> None:
    clock = ManualClock()
    logins = FailedLogins(burst=3, interval_s=2.0, clock=clock)
    for _ in range(3):
        assert logins.retry_after_s("203.0.113.9") == 0.0
        logins.failed("203.0.113.9")
    assert logins.retry_after_s("203.0.113.9") == 2.0
    assert logins.retry_after_s("203.0.113.10") == 0.0  # another address: unaffected
    assert logins.retry_after_s(None) == 0.0
    clock.now_s += 1.5
    assert logins.retry_after_s("203.0.113.9") == 0.5
    clock.now_s += 0.5
    assert logins.retry_after_s("203.0.113.9") == 0.0  # one more try
    logins.failed("203.0.113.9")
    assert logins.retry_after_s("203.0.113.9") == 2.0
    clock.now_s += 60
    assert logins.retry_after_s("203.0.113.9") == 0.0
    assert logins.failures == 4


def test_an_ipv6_slash_64_shares_one_budget() -> None:
    logins = FailedLogins(burst=2, interval_s=10.0, clock=ManualClock())
    logins.failed("2001:db8:1:2::1")
    logins.failed("2001:db8:1:2::ffff")  # another address of the same /64
    assert logins.retry_after_s("2001:db8:1:2:abcd::7") == 10.0
    assert logins.retry_after_s("2001:db8:1:3::1") == 0.0
    logins.failed("::ffff:203.0.113.9")  # an IPv4-mapped peer is its IPv4 address
    logins.failed("203.0.113.9")
    assert logins.retry_after_s("203.0.113.9") == 10.0


def test_the_table_is_bounded_and_evictions_counted() -> None:
    clock = ManualClock()
    logins = FailedLogins(burst=5, interval_s=1.0, max_addresses=3, clock=clock)
    for i in range(3):
        logins.failed(f"198.51.100.{i}")
    clock.now_s += 10  # 198.51.100.0-2 have their whole budget back
    logins.failed("198.51.100.3")  # forgets .0: nothing lost
    assert len(logins) == 3 and logins.evicted == 0
    logins.failed("198.51.100.4")  # forgets .1, whole again
    logins.failed("198.51.100.5")  # forgets .2, whole again
    logins.failed("198.51.100.6")  # forgets .3, which still held a failure: counted
    assert len(logins) == 3 and logins.evicted == 1


def test_log_lines_are_sampled_with_counts() -> None:
    clock = ManualClock()
    logins = FailedLogins(burst=1, interval_s=100.0, clock=clock)
    logins.failed("203.0.113.9")
    first = logins.log_line("203.0.113.9", "failed login")
    assert first is not None and first.startswith("failed login from 203.0.113.9")
    lines = []
    for _ in range(50):
        logins.refused()
        lines.append(logins.log_line("203.0.113.9", "token refused unhashed"))
    assert lines == [None] * 50
    clock.now_s += LOG_INTERVAL_S
    logins.failed("2001:db8::5")
    line = logins.log_line("2001:db8::5", "failed login")
    assert line == ("failed login from 2001:db8::/64; since the last such line: 1 failed "
                    "logins, 50 tokens refused unhashed (2 addresses over their budget)")


def test_the_hosts_own_loopback_address_has_no_budget() -> None:
    logins = FailedLogins(burst=1, interval_s=100.0, clock=ManualClock())
    for address in ("127.0.0.1", "::1", "::ffff:127.0.0.1", None):
        logins.failed(address)
        logins.failed(address)
        assert logins.retry_after_s(address) == 0.0
    assert len(logins) == 0 and logins.failures == 8
    logins.failed("127.0.0.9")  # another loopback address stands for another host in tests
    assert logins.retry_after_s("127.0.0.9") == 100.0


def test_a_failure_past_the_budget_still_costs_what_is_left() -> None:
    # (A GET of /healthz is answered whatever its token: a bad one still counts.)
    clock = ManualClock()
    logins = FailedLogins(burst=1, interval_s=2.0, clock=clock)
    logins.failed("203.0.113.9")
    clock.now_s += 1.0
    assert logins.retry_after_s("203.0.113.9") == 1.0
    logins.failed("203.0.113.9")  # half a token left: spent, the wait starts again
    assert logins.retry_after_s("203.0.113.9") == 2.0
