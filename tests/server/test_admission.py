"""The per-address bounds count an IPv6 /64 as one address (fleetctl.server.addressgroup)."""

from __future__ import annotations

from fleetctl.server.addressgroup import address_group
from fleetctl.server.admission import UnauthenticatedGate


def test_address_groups() -> None:
    assert address_group("203.0.113.9") == "203.0.113.9"
    assert address_group("::ffff:203.0.113.9") == "203.0.113.9"  # dual-stack IPv4 peer
    assert address_group("2001:db8:1:2:aaaa::1") == "2001:db8:1:2::/64"
    assert address_group("2001:db8:1:2:ffff:ffff:ffff:ffff") == "2001:db8:1:2::/64"
    assert address_group("2001:db8:1:3::1") == "2001:db8:1:3::/64"
    assert address_group("fe80::1%eth0") == "fe80::/64"
    assert address_group("::1") == "::/64"
    assert address_group("not an address") == "not an address"
    assert address_group(None) == "?"


def test_one_ipv6_host_cannot_fill_the_cap_from_its_own_addresses() -> None:
    gate = UnauthenticatedGate(100, 3)
    admitted = [gate.admit(f"2001:db8:1:2::{i:x}") for i in range(1, 5)]
    assert admitted == [None, None, None, "per_address"]
    assert gate.admit("2001:db8:1:3::1") is None  # the next /64 is another client
    assert gate.held("2001:db8:1:2::99") == 3
    gate.release("2001:db8:1:2::2")  # any address of the /64 gives its slot back
    assert gate.held("2001:db8:1:2::1") == 2
    assert gate.admit("2001:db8:1:2::abcd") is None
    assert gate.refused == {"total": 0, "per_address": 1}


def test_ipv4_mapped_peers_count_as_their_ipv4_address() -> None:
    gate = UnauthenticatedGate(100, 2)
    assert gate.admit("203.0.113.9") is None
    assert gate.admit("::ffff:203.0.113.9") is None
    assert gate.admit("::ffff:203.0.113.9") == "per_address"
    assert gate.admit("203.0.113.10") is None  # IPv4 addresses stay one client each
    gate.release("::ffff:203.0.113.9")
    gate.release("203.0.113.9")
    assert gate.held("203.0.113.9") == 0 and gate.open == 1


def test_an_exempt_proxy_counts_only_toward_the_total() -> None:
    gate = UnauthenticatedGate(4, 1, exempt=lambda a: a == "2001:db8::10")
    assert [gate.admit("2001:db8::10") for _ in range(3)] == [None, None, None]
    assert gate.admit("2001:db8::11") is None  # its /64 neighbour is not crowded out
    assert gate.admit("2001:db8::12") == "total"
    gate.release("2001:db8::10")
    assert gate.held("2001:db8::11") == 1 and gate.open == 3
