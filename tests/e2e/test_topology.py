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
from fleetctl.e2e.topology import ROBOT_SIDE, SERVER_SIDE, Topology

pytestmark = [
    pytest.mark.docker,
    pytest.mark.skipif(shutil.which("docker") is None, reason="needs docker"),
]

_IDLE = ["python3", "-c", "import signal; signal.sigwait({signal.SIGTERM, signal.SIGINT})"]

_SINK = (
    "import socket\n"
    "t=socket.socket(); t.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)\n"
    "t.bind(('0.0.0.0', 5001)); t.listen()\n"
    "while True:\n"
    "    c,_=t.accept(); h=c.recv(16).decode().strip(); n=int(h or 0); g=0\n"
    "    while g<n:\n"
    "        d=c.recv(65536)\n"
    "        if not d: break\n"
    "        g+=len(d)\n"
    "    c.sendall(b'k'); c.close()\n"
)

_SEND = (
    "import socket,sys,time\n"
    "n=int(sys.argv[2]); s=socket.create_connection((sys.argv[1],5001),timeout=20)\n"
    "s.sendall(f'{n:<16}'.encode()); t=time.monotonic(); s.sendall(bytes(n))\n"
    "assert s.recv(1)==b'k'; print(n*8/(time.monotonic()-t))\n"
)

_PROBE = (
    "import socket,sys\n"
    "s=socket.socket(); s.settimeout(float(sys.argv[2]))\n"
    "try:\n"
    "    s.connect((sys.argv[1],5001)); print('open')\n"
    "except OSError:\n"
    "    print('dropped')\n"
)


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
    server = topo.start("server", SERVER_SIDE, BASE_IMAGE, ["python3", "-c", _SINK])
    robot = topo.start("robot", ROBOT_SIDE, BASE_IMAGE, _IDLE)
    caps = topo.capabilities()
    assert caps.tbf or caps.htb or caps.netem
    uplink = topo.shaper("uplink", caps)

    # The sink listens once its container runs python; wait for it with a deadline.
    deadline = time.monotonic() + 15.0
    while topo.exec(robot.name, ["python3", "-c", _PROBE, server.ip, "1"]).stdout.strip() != (
        "open"
    ):
        assert time.monotonic() < deadline, topo.logs(server.name)

    uplink.set_rate(RateSpec(mbit(8)))
    res = topo.exec(robot.name, ["python3", "-c", _SEND, server.ip, "1000000"])
    assert res.returncode == 0, res.stderr
    rate = float(res.stdout)
    print(f"uplink shaped to 8 Mbit/s carried {rate / 1e6:.2f} Mbit/s")
    assert mbit(8) * 0.7 < rate < mbit(8) * 1.15

    uplink.cut()
    probe = topo.exec(robot.name, ["python3", "-c", _PROBE, server.ip, "0.5"])
    assert probe.stdout.strip() == "dropped"
    uplink.restore()
    probe = topo.exec(robot.name, ["python3", "-c", _PROBE, server.ip, "5"])
    assert probe.stdout.strip() == "open"
    # The robot's kernel counters are what the multi-consumer scenario reads.
    assert topo.tx_bytes(robot.name) > 1_000_000


def test_no_container_has_a_route_out(topo: Topology) -> None:
    for name in [topo.router, *(e.name for e in topo.endpoints)]:
        routes = topo.exec(name, ["ip", "route", "show", "default"])
        assert routes.returncode == 0 and routes.stdout.strip() == "", (name, routes.stdout)
