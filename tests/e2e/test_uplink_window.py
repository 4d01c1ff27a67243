"""The multi-consumer uplink window: whole publish periods, clock and counter read together."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Sequence

import pytest

from fleetctl.deploy.dockercli import Completed
from fleetctl.e2e.scenarios import window_s
from fleetctl.e2e.topology import Topology


@pytest.mark.parametrize(("duration_s", "rate_hz", "expected_s"), [
    (6.0, 5.0, 2.0), (30.0, 5.0, 6.0), (7.0, 5.0, 2.0), (11.0, 5.0, 2.2), (30.0, 3.0, 6.0),
    (1.0, 0.25, 4.0),
])
def test_the_window_is_whole_publish_periods(duration_s: float, rate_hz: float,
                                             expected_s: float) -> None:
    assert window_s(duration_s, rate_hz) == pytest.approx(expected_s)
    assert (window_s(duration_s, rate_hz) * rate_hz) == pytest.approx(
        round(window_s(duration_s, rate_hz) * rate_hz))


def test_count_tx_runs_its_script_in_the_container_and_times_it_there() -> None:
    calls: list[list[str]] = []

    def local(argv: Sequence[str], stdin: bytes | None, capture: bool) -> Completed:
        # `docker exec -u root NAME python3 -c SCRIPT ...` run here, on the loopback device.
        calls.append(list(argv))
        assert list(argv[:5]) == ["docker", "exec", "-u", "root", "router"]
        res = subprocess.run([sys.executable, *argv[6:]], capture_output=True, text=True,
                             check=False)
        return Completed(tuple(argv), res.returncode, res.stdout, res.stderr)

    window = Topology("t1", local, owner="h:1:2").count_tx("router", "lo", 0.2)
    assert window.seconds == pytest.approx(0.2, abs=0.05)
    assert window.seconds >= 0.2 and window.tx_bytes >= 0
    assert calls[0][-2:] == ["lo", "0.2"]
