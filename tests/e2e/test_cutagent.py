"""The router's cut agent (fleetctl.e2e.cutagent), run in a network namespace the test
makes (no docker): one process for every cut, the clock read when the routes changed."""

from __future__ import annotations

import secrets
import subprocess
import time
from collections.abc import Iterator

import pytest

from fleetctl.e2e.cutagent import CutAgent
from fleetctl.errors import FleetError
from tests.netns import NEEDS_ROOT

pytestmark = [pytest.mark.netns, NEEDS_ROOT]

HALVES = ["10.213.0.0/17", "10.213.128.0/17"]


@pytest.fixture
def namespace() -> Iterator[str]:
    name = f"fleetctl-cut-{secrets.token_hex(3)}"
    subprocess.run(["ip", "netns", "add", name], check=True)
    try:
        yield name
    finally:
        subprocess.run(["ip", "netns", "del", name], check=False)


def blackholes(ns: str) -> str:
    return subprocess.run(["ip", "-n", ns, "route", "show", "type", "blackhole"],
                          capture_output=True, text=True, check=True).stdout


def test_one_process_cuts_and_restores_and_reads_the_clock_when_it_did(namespace: str) -> None:
    agent = CutAgent("test", argv_prefix=["ip", "netns", "exec", namespace])
    try:
        before = time.time_ns()
        cut, left = agent.change("replace", HALVES)
        assert before <= cut <= time.time_ns()
        assert sorted(left.split()[1::2]) == sorted(HALVES)  # "blackhole <cidr>" per route
        assert all(h in blackholes(namespace) for h in HALVES)
        pid = agent._proc.pid if agent._proc else None
        restore, left = agent.change("del", HALVES)
        assert cut < restore <= time.time_ns()
        assert left.strip() == "" and blackholes(namespace).strip() == ""
        again, _ = agent.change("del", HALVES)  # nothing left to remove is not an error
        assert again > restore
        assert agent._proc is not None and agent._proc.pid == pid  # the same process
    finally:
        agent.close()
    assert agent._proc is None


def test_a_route_the_kernel_refuses_is_an_error_naming_it(namespace: str) -> None:
    agent = CutAgent("test", argv_prefix=["ip", "netns", "exec", namespace])
    try:
        with pytest.raises(FleetError, match="blackhole routes replace in test"):
            agent.change("replace", ["10.213.0.0/33"])
        cut, _ = agent.change("replace", HALVES)  # the agent goes on after an error
        assert cut > 0
    finally:
        agent.close()


def test_an_agent_that_cannot_start_is_an_error_with_its_output() -> None:
    agent = CutAgent("nowhere", argv_prefix=["ip", "netns", "exec", "fleetctl-no-such-ns"])
    with pytest.raises(FleetError, match="cut agent in nowhere: it exited;"):
        agent.change("replace", HALVES)


def test_a_request_that_is_not_a_route_change_is_refused() -> None:
    agent = CutAgent("test", argv_prefix=[])
    with pytest.raises(ValueError):
        agent.change("add", HALVES)
    with pytest.raises(ValueError):
        agent.change("del", ["10.0.0.0/8 via 1.2.3.4"])
    assert agent._proc is None  # nothing was started
