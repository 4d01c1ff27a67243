"""The load publisher's timer phases (:func:`fleetctl.e2e.load.phase_schedule`): pure, no ROS.
The clock itself runs in every docker e2e scenario with the ``peer`` profile."""

from __future__ import annotations

from dataclasses import replace

import pytest

from fleetctl.e2e.load import phase_schedule
from fleetctl.e2e.profiles import profile
from fleetctl.errors import FleetError


def test_the_peer_load_puts_its_scan_and_its_pose_25_ms_apart() -> None:
    schedule = phase_schedule(profile("peer"))
    assert schedule is not None
    base, slots = schedule
    assert base == pytest.approx(0.025)
    assert slots == [(4, 0), (2, 1)]  # the scan every 4th tick from 0, the pose every 2nd from 1
    ticks = {i: [k for k in range(8) if k % every == at] for i, (every, at) in enumerate(slots)}
    assert ticks == {0: [0, 4], 1: [1, 3, 5, 7]}  # never on the same tick


def test_profiles_that_do_not_spread_keep_a_timer_per_topic() -> None:
    assert phase_schedule(profile("dropout")) is None


def test_a_rate_off_the_clock_s_grid_is_refused_naming_the_topic() -> None:
    peer = profile("peer")
    odd = replace(peer, topics=(peer.topics[0], replace(peer.topics[1], rate_hz=7.0)))
    with pytest.raises(FleetError, match="/pose at 7 Hz"):
        phase_schedule(odd)
