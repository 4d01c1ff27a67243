"""``fleetctl client`` as a process: its counters while it runs (SIGUSR1)."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

from fleetctl.waiting import wait_until
from tests.client.ros.harness import JsonProc, fleetctl_argv

pytestmark = pytest.mark.ros
DOMAIN_ID = 74  # this file's own ROS domain
STARTUP_S = 30.0


def test_sigusr1_logs_the_counters_of_a_running_client(tmp_path: Path) -> None:
    """The counters (drops, losses before the client, link state) were printed only at
    exit with --print-stats: a running robot's could not be read."""
    config = tmp_path / "client.yaml"
    config.write_text("server_url: ws://127.0.0.1:1/\nrobot_name: r1\npublish:\n"
                      "  - {topic: /scan, type: sensor_msgs/msg/LaserScan}\n")
    log = tmp_path / "client.log"
    client = JsonProc(fleetctl_argv("client", "--config", str(config)),
                      {"ROS_DOMAIN_ID": str(DOMAIN_ID)}, log)

    def logged(text: str) -> list[str]:
        return [line for line in log.read_text().splitlines() if text in line]

    try:
        wait_until(lambda: logged("client r1: 1 topics out"), STARTUP_S, describe="start")
        client.signal(signal.SIGUSR1)
        wait_until(lambda: logged("stats: "), STARTUP_S, describe="the stats line")
        stats = json.loads(logged("stats: ")[0].split("stats: ", 1)[1])
        assert stats["connected"] is False and stats["connect_failures"] >= 0
        assert stats["bridge"]["lost_before_client"] == 0
        assert stats["bridge"]["per_topic_lost"] == {}
        assert client.process.poll() is None  # still running
    finally:
        assert client.stop() == 0, client.stderr_tail()
