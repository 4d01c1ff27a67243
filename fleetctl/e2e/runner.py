"""Run e2e scenarios in the router topology and collect results for the report.

Scenarios (MISSION.md "End-to-end runs"; parameters are the issue's):

- ``link``: calibration of the topology itself: raw TCP through the router at each shaped
  rate and a cut, so every other number can be read against what the link really carries.
- ``dropout``, ``multi-consumer``, ``ramp``, ``priority``: the fleet (server, robot client,
  consumers) over the shaped link. They need the ``fleetctl server`` and ``fleetctl client``
  commands in the images; a preflight checks that and reports ``not_run`` (a failure) with
  the reason instead of pretending. The server is the container ``fleetctl up`` deploys
  (:mod:`fleetctl.e2e.deployment`). With WireGuard (``--wireguard auto|on``; off by default
  for now, docs/e2e.md) robots reach it through the tunnel, as ``up`` deploys them; the
  tunnel's UDP crosses the same shaped router.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fleetctl.deploy.dockercli import Runner, image_exists, subprocess_runner
from fleetctl.deploy.images import BASE_IMAGE, image_tag
from fleetctl.deploy.shaping import Capabilities, RateSpec, mbit
from fleetctl.e2e import cleanup, wireguard
from fleetctl.e2e.deployment import Deployment
from fleetctl.e2e.fleetrun import FleetRun
from fleetctl.e2e.scenarios import SCENARIO_FUNCS
from fleetctl.e2e.topology import IDLE_COMMAND, ROBOT_SIDE, SERVER_SIDE, Topology
from fleetctl.errors import EnvironmentMissing, FleetError

Progress = Callable[[str], None]
SCENARIOS = ("link", "dropout", "multi-consumer", "ramp", "priority", "peer", "peer-fanout",
             "peer-large", "replica-failure")
# Components each fleet scenario runs: (image, command that must exist in it).
_NEEDS = {
    "dropout": (("server", "server"), ("client", "client")),
    "multi-consumer": (("server", "server"), ("client", "client")),
    "ramp": (("server", "server"), ("client", "client")),
    "priority": (("server", "server"), ("client", "client")),
    "peer": (("server", "server"), ("client", "client")),
    "peer-fanout": (("server", "server"), ("client", "client")),
    "peer-large": (("server", "server"), ("client", "client")),
    "replica-failure": (("server", "server"), ("client", "client")),
}
# The link calibration probe: a TCP sink on the server side, a timed sender on the robot side.
SINK_SCRIPT = (
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
SEND_SCRIPT = (
    "import socket,sys,time\n"
    "n=int(sys.argv[2]); s=socket.create_connection((sys.argv[1],5001),timeout=30)\n"
    "s.sendall(f'{n:<16}'.encode()); t=time.monotonic(); s.sendall(bytes(n))\n"
    "assert s.recv(1)==b'k'; print(n*8/(time.monotonic()-t))\n"
)
PROBE_SCRIPT = (
    "import socket,sys\n"
    "s=socket.socket(); s.settimeout(float(sys.argv[2]))\n"
    "try:\n"
    "    s.connect((sys.argv[1],5001)); print('open')\n"
    "except OSError:\n"
    "    print('dropped')\n"
)


@dataclass(frozen=True)
class RunConfig:
    """One ``fleetctl e2e`` invocation.

    Attributes:
        scenarios: Which scenarios, in order.
        duration_s: Length of each scenario's measured phase (seconds); the short CI run
            uses a few seconds, the documented full run 30.
        work_dir: Where configs and raw sample files go (mounted at ``/e2e``); None
            means a new temporary directory. Its ``out/`` is emptied first.
        source_dir: Mount this checkout's ``fleetctl/`` over the images' package
            (development without ``fleetctl build``); None runs the images as built.
        wireguard: ``auto`` (WireGuard when ``/dev/net/tun`` exists), ``on`` or ``off``
            (the default until dropout's recovery holds over the tunnel in every run,
            docs/e2e.md).
        run_id: Id of the run in container names and labels (at most 8 of ``a-z0-9``);
            None: random.
    """

    scenarios: tuple[str, ...] = SCENARIOS
    duration_s: float = 30.0
    work_dir: Path | None = None
    source_dir: Path | None = None
    wireguard: str = "auto"
    run_id: str | None = None


def _crit(name: str, value: float, bound: float, ok: bool) -> dict[str, Any]:
    return {"name": name, "value": value, "bound": bound, "ok": ok}


def preflight(runner: Runner = subprocess_runner) -> None:
    """Check the images exist.

    Raises:
        EnvironmentMissing: an image is missing (run ``fleetctl build``).
    """
    for image in (BASE_IMAGE, image_tag("router")):
        if not image_exists(runner, image):
            raise EnvironmentMissing(f"image {image} is missing: run `fleetctl build` first")


def missing_components(scenario: str, runner: Runner = subprocess_runner,
                       mounts: Sequence[str] = (), labels: Sequence[str] = ()) -> list[str]:
    """The ``image: command`` pairs *scenario* needs that do not work (empty: all present).

    Args:
        labels: ``--label`` arguments for the probe containers (the run's).
    """
    missing = []
    volumes = [arg for m in mounts for arg in ("-v", m)]
    for image, command in _NEEDS.get(scenario, ()):
        tag = image_tag(image)
        res = runner(["docker", "run", "--rm", "--network", "none", *labels, *volumes, tag,
                      "fleetctl", command, "--help"], None, True)
        if res.returncode != 0:
            missing.append(f"{tag}: `fleetctl {command}`")
    return missing


class _Link:
    """Raw TCP sender (robot side) and sink (server side) to calibrate the shaped link."""

    def __init__(self, topo: Topology) -> None:
        self.topo = topo
        self.sink = topo.start("sink", SERVER_SIDE, BASE_IMAGE, ["python3", "-c", SINK_SCRIPT])
        self.robot = topo.start("sender", ROBOT_SIDE, BASE_IMAGE, IDLE_COMMAND)

    def probe(self, timeout_s: float) -> bool:
        res = self.topo.exec(self.robot.name, ["python3", "-c", PROBE_SCRIPT, self.sink.ip,
                                               str(timeout_s)])
        return res.stdout.strip() == "open"

    def wait_open(self, deadline_s: float) -> float:
        """Seconds until a TCP connect through the router succeeds (inf at the deadline)."""
        start = time.monotonic()
        while time.monotonic() - start < deadline_s:
            if self.probe(0.5):
                return time.monotonic() - start
        return float("inf")

    def carried_bit_s(self, nbytes: int) -> float:
        res = self.topo.exec(self.robot.name, ["python3", "-c", SEND_SCRIPT, self.sink.ip,
                                               str(nbytes)])
        return float(res.stdout) if res.returncode == 0 else 0.0


def run_link(topo: Topology, caps: Capabilities, cfg: RunConfig,
             progress: Progress) -> dict[str, Any]:
    """Calibrate the router: carried rate at 100/12/6/4 Mbit and a cut and restore."""
    link = _Link(topo)
    uplink = topo.shaper("uplink", caps)
    criteria, notes = [], [f"tc: {caps.describe()}", "raw TCP through the router, no fleetctl"]
    if link.wait_open(15.0) == float("inf"):
        return {"name": "link", "status": "fail", "criteria": [], "notes": [
            *notes, "no TCP connection through the router: " + topo.logs(link.sink.name)]}
    rates, carried = [100, 12, 6, 4], []
    # Each transfer lasts about a fifth of the duration, at least ~0.5 s.
    seconds = max(0.5, cfg.duration_s / 5 / len(rates))
    for rate in rates:
        uplink.set_rate(RateSpec(mbit(rate)))
        got = link.carried_bit_s(int(mbit(rate) / 8 * seconds))
        carried.append(got / 1e6)
        progress(f"link: shaped {rate} Mbit/s, carried {got / 1e6:.2f} Mbit/s")
        criteria.append(_crit(f"carried_at_{rate}mbit_ratio", got / mbit(rate), 0.85,
                              got >= 0.85 * mbit(rate)))
    uplink.cut()
    cut_dropped = not link.probe(0.5)
    uplink.restore()
    back_s = link.wait_open(5.0)
    progress(f"link: cut dropped traffic: {cut_dropped}; back after restore in {back_s:.3f} s")
    criteria.append(_crit("cut_drops_traffic", float(cut_dropped), 1.0, cut_dropped))
    criteria.append(_crit("reconnect_after_restore_s", back_s, 1.0, back_s < 1.0))
    uplink.clear()
    return {
        "name": "link",
        "status": "pass" if all(c["ok"] for c in criteria) else "fail",
        "criteria": criteria,
        "notes": notes,
        "commands": [" ".join(c) for c in uplink.commands],
        "plots": [{"title": "carried rate through the router", "xlabel": "shaped rate (Mbit/s)",
                   "ylabel": "carried (Mbit/s)", "marker": "o",
                   "lines": {"carried": [rates, carried], "shaped": [rates, rates]}}],
    }


def run(cfg: RunConfig, progress: Progress = print,
        runner: Runner | None = None) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Run *cfg*'s scenarios; returns the environment description and one result each.

    Args:
        runner: Runs the docker commands (default: :func:`cleanup.run_runner`, each command
            with a deadline).

    Raises:
        EnvironmentMissing: images are missing, or ``--wireguard on`` without a TUN device.
        Interrupted: a signal stopped the run (with :class:`SignalGuard` active); every
            container and network of the run was removed first.
    """
    mode = wireguard.decide(cfg.wireguard)
    # A runner of the caller's (a unit test's) also does the cleanup; ours retries it.
    cleanup_runner = None if runner else cleanup.CLEANUP_RUNNER
    runner = runner or cleanup.run_runner(cfg.duration_s)
    preflight(runner)
    results: list[dict[str, Any]] = []
    work = cfg.work_dir or Path(tempfile.mkdtemp(prefix="fleetctl-e2e-"))
    shutil.rmtree(work / "out", ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    topology = Topology(runner=runner, cleanup_runner=cleanup_runner)
    if cfg.run_id is not None:
        topology.run_id = cfg.run_id
    with topology as topo:
        progress(f"run {topo.run_id} (label {cleanup.RUN_LABEL}={topo.run_id})")
        link_mtu = topo.mtu(topo.router, topo.router_devs[ROBOT_SIDE])
        deployment = Deployment(work.resolve(), topo.run_id, mode.on,
                                wireguard.tunnel_mtu(link_mtu), cfg.source_dir)
        fleet = FleetRun(topo, work.resolve(), deployment)
        fleet.pin_images("server", "client")
        caps = topo.capabilities()
        # The shaper's own cut (bfifo limit 0) would also stop ARP: the scenarios cut with
        # blackhole routes in the router instead (scenarios.Link says why).
        shaping = caps.describe().replace(f"cut: {caps.cut_method}",
                                          "cut: blackhole routes in the router")
        env = {"tc": shaping, "router": topo.router, "duration_s": cfg.duration_s,
               "clock": "one host clock (containers share the kernel's CLOCK_REALTIME)",
               "wireguard": _describe_wireguard(mode, deployment, link_mtu),
               "server": "the `server` service `fleetctl up` renders (compose.server_service), "
                         "as `docker run` arguments, without ports, restart policy or static "
                         "address; consumers on its HTTPS port (peer, peer-fanout: beside it, "
                         "on its plain listener over loopback)"}
        progress(f"topology up; {shaping}")
        progress(f"wireguard: {env['wireguard']}")
        for i, name in enumerate(cfg.scenarios, 1):
            progress(f"[{i}/{len(cfg.scenarios)}] scenario {name}")
            if name == "link":
                results.append(run_link(topo, caps, cfg, progress))
                continue
            results.append(_fleet_scenario(name, fleet, caps, cfg, progress))
    return env, results


def _describe_wireguard(mode: wireguard.Mode, deployment: Deployment,
                        link_mtu: int) -> str:
    """The report's ``wireguard`` line: on or off, and why."""
    if not mode.on:
        return mode.describe()
    return (f"{mode.describe()}; robot tunnel MTU {deployment.mtu_bytes} on a {link_mtu}-byte "
            "link (the server's: up's default); the link scenario and the DDS baseline use "
            "the routed network")


def _fleet_scenario(name: str, fleet: FleetRun, caps: Capabilities, cfg: RunConfig,
                    progress: Progress) -> dict[str, Any]:
    """Run one fleet scenario; a component that cannot start makes it ``not_run``."""
    missing = missing_components(name, fleet.topo.runner, fleet.mounts(), fleet.topo.labels)
    if missing:
        reason = "needs " + ", ".join(missing)
        progress(f"{name}: NOT RUN: {reason}")
        return {"name": name, "status": "not_run", "criteria": [], "notes": [f"not run: {reason}"]}
    try:
        if fleet.server is None:
            fleet.start_server()
            progress(f"server up at {fleet.server_url}")
        return SCENARIO_FUNCS[name](fleet, caps, cfg.duration_s, progress)
    except FleetError as exc:
        progress(f"{name}: FAILED to run: {exc}")
        return {"name": name, "status": "not_run", "criteria": [],
                "notes": [f"could not run: {exc}"]}
