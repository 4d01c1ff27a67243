"""The e2e topology for real: traffic robot -> server crosses the router and its tc shaping.

Needs Docker and the images ``fleetctl build`` makes (base and router). Only the two
networks this test creates carry traffic (no container keeps a default route).
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator

import pytest

from fleetctl.deploy.dockercli import image_exists, subprocess_runner
from fleetctl.deploy.images import BASE_IMAGE, image_tag
from fleetctl.deploy.shaping import RateSpec, mbit
from fleetctl.e2e.runner import PROBE_SCRIPT, SEND_SCRIPT, SINK_SCRIPT
from fleetctl.e2e.topology import IDLE_COMMAND, ROBOT_SIDE, SERVER_SIDE, Topology

pytestmark = [
    pytest.mark.docker,
    pytest.mark.skipif(shutil.which("docker") is None, reason="needs docker"),
]


@pytest.fixture(scope="module")
def topo() -> Iterator[Topology]:
    for image in (BASE_IMAGE, image_tag("router")):
        if not image_exists(subprocess_runner, image):
            pytest.fail(f"{image} missing: run `fleetctl build` first")
    topology = Topology()
    try:
        topology.create()
        yield topology
    finally:
        topology.close()


def test_router_shapes_the_uplink_and_cuts_it(topo: Topology) -> None:
    server = topo.start("server", SERVER_SIDE, BASE_IMAGE, ["python3", "-c", SINK_SCRIPT])
    robot = topo.start("robot", ROBOT_SIDE, BASE_IMAGE, IDLE_COMMAND)
    caps = topo.capabilities()
    assert caps.tbf or caps.htb or caps.netem
    uplink = topo.shaper("uplink", caps)

    # The sink listens once its container runs python; wait for it with a deadline.
    deadline = time.monotonic() + 15.0
    while topo.exec(robot.name, ["python3", "-c", PROBE_SCRIPT, server.ip, "1"]).stdout.strip() != (
        "open"
    ):
        assert time.monotonic() < deadline, topo.logs(server.name)

    uplink.set_rate(RateSpec(mbit(8)))
    res = topo.exec(robot.name, ["python3", "-c", SEND_SCRIPT, server.ip, "1000000"])
    assert res.returncode == 0, res.stderr
    rate = float(res.stdout)
    print(f"uplink shaped to 8 Mbit/s carried {rate / 1e6:.2f} Mbit/s")
    assert mbit(8) * 0.7 < rate < mbit(8) * 1.15

    uplink.cut()
    probe = topo.exec(robot.name, ["python3", "-c", PROBE_SCRIPT, server.ip, "0.5"])
    assert probe.stdout.strip() == "dropped"
    uplink.restore()
    probe = topo.exec(robot.name, ["python3", "-c", PROBE_SCRIPT, server.ip, "5"])
    assert probe.stdout.strip() == "open"
    # The robot's kernel counters are what the multi-consumer scenario reads.
    assert topo.tx_bytes(robot.name) > 1_000_000


def test_no_container_has_a_route_out(topo: Topology) -> None:
    for name in [topo.router, *(e.name for e in topo.endpoints)]:
        routes = topo.exec(name, ["ip", "route", "show", "default"])
        assert routes.returncode == 0 and routes.stdout.strip() == "", (name, routes.stdout)


def test_blackhole_cut_drops_ip_both_ways_but_not_arp(topo: Topology) -> None:
    server = topo.start("bh-server", SERVER_SIDE, BASE_IMAGE, ["python3", "-c", SINK_SCRIPT])
    robot = topo.start("bh-robot", ROBOT_SIDE, BASE_IMAGE, IDLE_COMMAND)
    deadline = time.monotonic() + 15.0
    while topo.exec(robot.name, ["python3", "-c", PROBE_SCRIPT, server.ip, "1"]).stdout.strip() != (
        "open"
    ):
        assert time.monotonic() < deadline, topo.logs(server.name)
    for side in (SERVER_SIDE, ROBOT_SIDE):
        topo.blackhole(side, True)
        topo.blackhole(side, True)  # idempotent: a second cut is not an error
    try:
        probe = topo.exec(robot.name, ["python3", "-c", PROBE_SCRIPT, server.ip, "0.5"])
        assert probe.stdout.strip() == "dropped"
        # The server's neighbour entry for the router still resolves during the cut.
        neigh = topo.exec(server.name, ["ip", "neigh", "flush", "all"])
        assert neigh.returncode == 0, neigh.stderr
        gateway = topo.router_ips[SERVER_SIDE]
        ping_arp = topo.exec(server.name, ["python3", "-c", _ARP_SCRIPT, gateway])
        assert ping_arp.stdout.strip() in ("REACHABLE", "STALE", "DELAY"), ping_arp.stdout
    finally:
        for side in (SERVER_SIDE, ROBOT_SIDE):
            topo.blackhole(side, False)
    topo.blackhole(SERVER_SIDE, False)  # removing what is gone is not an error
    probe = topo.exec(robot.name, ["python3", "-c", PROBE_SCRIPT, server.ip, "5"])
    assert probe.stdout.strip() == "open"


# Sends one UDP datagram to the gateway's discard port (which makes the kernel resolve its
# address), then waits up to 3 s for the neighbour entry to leave INCOMPLETE; prints its state.
_ARP_SCRIPT = """
import socket, subprocess, sys, time
gw = sys.argv[1]
socket.socket(socket.AF_INET, socket.SOCK_DGRAM).sendto(b"x", (gw, 9))
deadline = time.monotonic() + 3.0
state = ""
while time.monotonic() < deadline:
    out = subprocess.run(["ip", "neigh", "show", gw], capture_output=True, text=True).stdout
    state = out.split()[-1] if out.split() else ""
    if state not in ("", "INCOMPLETE"):
        break
    time.sleep(0.05)
print(state)
"""


def test_both_sides_cut_and_restored_in_one_command_timed_by_the_router(
        topo: Topology) -> None:
    server = topo.start("bh2-server", SERVER_SIDE, BASE_IMAGE, ["python3", "-c", SINK_SCRIPT])
    robot = topo.start("bh2-robot", ROBOT_SIDE, BASE_IMAGE, IDLE_COMMAND)
    deadline = time.monotonic() + 15.0
    while topo.exec(robot.name, ["python3", "-c", PROBE_SCRIPT, server.ip, "1"]).stdout.strip() != (
        "open"
    ):
        assert time.monotonic() < deadline, topo.logs(server.name)
    before = time.time_ns()
    cut = topo.blackhole_all(True)
    try:
        assert before <= cut <= time.time_ns()
        probe = topo.exec(robot.name, ["python3", "-c", PROBE_SCRIPT, server.ip, "0.5"])
        assert probe.stdout.strip() == "dropped"
    finally:
        restore = topo.blackhole_all(False)
    assert cut < restore <= time.time_ns()
    assert topo.blackhole_all(False) > restore  # nothing left to remove is not an error
    probe = topo.exec(robot.name, ["python3", "-c", PROBE_SCRIPT, server.ip, "5"])
    assert probe.stdout.strip() == "open"
