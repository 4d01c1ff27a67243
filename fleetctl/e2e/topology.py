"""The e2e topology: a robot network, a server network, and a router that shapes between.

::

    robot containers --[robot net]-- router --[server net]-- server, consumers
                                     tc on eth(robot side): downlink (to robots)
                                     tc on eth(server side): uplink (from robots)

Both networks are plain Docker bridges (an ``--internal`` network's iptables rules drop
routed traffic whose source or destination is outside its subnet, which is all of ours), but
every container, router included, has its default route deleted: they reach each other only
through the router, and nothing outside the machine. Each endpoint container gets NET_ADMIN
so the runner can set its routes. Driven with the docker CLI; :meth:`Topology.close`
removes everything it made: by name, and by the run's label (:mod:`fleetctl.e2e.cleanup`),
which also finds a container whose ``docker run`` was interrupted before it returned. The
removal runs with signals deferred (:func:`fleetctl.e2e.interrupt.deferred`).
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import secrets
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from fleetctl.deploy.dockercli import Completed, Runner, check, subprocess_runner
from fleetctl.deploy.dockerrun import run_args
from fleetctl.deploy.images import image_tag
from fleetctl.deploy.shaping import Capabilities, LinkShaper, detect
from fleetctl.e2e import cleanup
from fleetctl.e2e.cutagent import CutAgent
from fleetctl.e2e.interrupt import deferred
from fleetctl.errors import FleetError

ROBOT_SIDE = "robot"
SERVER_SIDE = "server"
# A container command that does nothing until it is told to stop (a process to exec into).
IDLE_COMMAND = ["python3", "-c", "import signal; signal.sigwait({signal.SIGTERM, signal.SIGINT})"]


# Run in a container: the counter of argv[1] at now and at now + argv[2] seconds, each
# read right after the clock (CLOCK_REALTIME, shared by every container of the host).
_TX_WINDOW = (
    "import sys, time\n"
    "path = f'/sys/class/net/{sys.argv[1]}/statistics/tx_bytes'\n"
    "def read():\n"
    "    t = time.time_ns()\n"
    "    with open(path) as f:\n"
    "        return t, int(f.read())\n"
    "a = read(); end = a[0] + int(float(sys.argv[2]) * 1e9)\n"
    "while (left := end - time.time_ns()) > 0:\n"
    "    time.sleep(left / 1e9)\n"
    "b = read(); print(*a, *b)\n"
)


@dataclass(frozen=True)
class TxWindow:
    """Bytes sent during a measured window (times in ns since the epoch)."""

    start_ns: int
    end_ns: int
    tx_bytes: int

    @property
    def seconds(self) -> float:
        """The window's length (s)."""
        return (self.end_ns - self.start_ns) / 1e9


@dataclass(frozen=True)
class Endpoint:
    """A container in the topology: its name, side and address on its network."""

    name: str
    side: str
    ip: str


@dataclass
class Topology:
    """Networks, router and endpoints of one e2e run.

    Args:
        run_id: Unique suffix of every name and value of its run label (default: random).
        runner: Runs docker commands (replaceable in unit tests).
        router_image: Image of the router (iproute2 + python3).
        owner: Owner label value (default: this process, :func:`cleanup.owner`).
        cleanup_runner: Runs the removal in :meth:`close` (default: *runner*); the e2e run
            gives it :data:`cleanup.CLEANUP_RUNNER`, which retries a hung command.
    """

    run_id: str = field(default_factory=lambda: secrets.token_hex(3))
    runner: Runner = subprocess_runner
    owner: str = field(default_factory=cleanup.owner)
    router_image: str = image_tag("router")
    networks: dict[str, str] = field(default_factory=dict)  # side -> network name
    subnets: dict[str, str] = field(default_factory=dict)  # side -> CIDR
    router_ips: dict[str, str] = field(default_factory=dict)  # side -> router address
    router_devs: dict[str, str] = field(default_factory=dict)  # side -> router interface
    endpoints: list[Endpoint] = field(default_factory=list)
    router: str = ""
    cleanup_runner: Runner | None = None
    _cut_agent: CutAgent | None = field(default=None, repr=False)

    @property
    def labels(self) -> list[str]:
        """``--label`` arguments every container and network of this run gets."""
        return cleanup.label_args(self.run_id, self.owner)

    def _docker(self, *args: str, what: str) -> Completed:
        return check(self.runner(["docker", *args], None, True), what)

    def exec(self, container: str, argv: Sequence[str], *, user: str = "root") -> Completed:
        """Run *argv* in *container* (never raises; the caller checks the exit code)."""
        return self.runner(["docker", "exec", "-u", user, container, *argv], None, True)

    def create(self) -> None:
        """Make both networks and start the router; read its interfaces."""
        for side in (ROBOT_SIDE, SERVER_SIDE):
            name = f"fce2e-{self.run_id}-{side}"
            self._docker("network", "create", *self.labels, name,
                         what=f"network create {name}")
            self.networks[side] = name
            info = json.loads(self._docker("network", "inspect", name, what="inspect").stdout)
            self.subnets[side] = info[0]["IPAM"]["Config"][0]["Subnet"]
        self.router = f"fce2e-{self.run_id}-router"
        self._docker(
            "run", "-d", "--name", self.router, *self.labels, "--cap-add", "NET_ADMIN",
            "--sysctl", "net.ipv4.ip_forward=1", "--network", self.networks[ROBOT_SIDE],
            self.router_image, what="start router",
        )
        self._docker("network", "connect", self.networks[SERVER_SIDE], self.router,
                     what="connect router")
        self._read_router_interfaces()
        check(self.exec(self.router, ["ip", "route", "del", "default"]), "router routes")

    def _read_router_interfaces(self) -> None:
        out = check(self.exec(self.router, ["ip", "-o", "-4", "addr", "show"]), "router ip addr")
        for line in out.stdout.splitlines():
            parts = line.split()
            dev, addr = parts[1].split("@")[0], ipaddress.ip_interface(parts[3])
            for side, subnet in self.subnets.items():
                if addr.ip in ipaddress.ip_network(subnet):
                    self.router_devs[side], self.router_ips[side] = dev, str(addr.ip)
        if set(self.router_devs) != {ROBOT_SIDE, SERVER_SIDE}:
            raise FleetError(f"router interfaces not found in: {out.stdout.strip()}")

    def start(
        self, role: str, side: str, image: str, command: Sequence[str], *,
        env: Mapping[str, str] | None = None, mounts: Sequence[str] = (),
        user: str | None = None, devices: Sequence[str] = (),
        hosts: Mapping[str, str] | None = None,
    ) -> Endpoint:
        """Start a container on *side* and route the other side's subnet via the router.

        Args:
            role: Short name (``server``, ``robot``, ``consumer3``).
            side: :data:`ROBOT_SIDE` or :data:`SERVER_SIDE`.
            image: Image to run.
            command: Its command.
            env: Environment variables.
            mounts: ``-v`` specifications.
            user: Run as this user (default: the image's).
            devices: ``--device`` specifications (``/dev/net/tun`` for WireGuard).
            hosts: Names to resolve in the container (``--add-host NAME:IP``).
        """
        name = self.container_name(role)
        argv = ["run", "-d", "--name", name, *self._endpoint_args(role, side)]
        for device in devices:
            argv += ["--device", device]
        for key, value in (env or {}).items():
            argv += ["-e", f"{key}={value}"]
        for mount in mounts:
            argv += ["-v", mount]
        for host, ip in (hosts or {}).items():
            argv += ["--add-host", f"{host}:{ip}"]
        if user:
            argv += ["-u", user]
        self._docker(*argv, image, *command, what=f"start {role}")
        return self._attach(name, role, side)

    def start_beside(self, role: str, beside: Endpoint, image: str,
                     command: Sequence[str], *, mounts: Sequence[str] = ()) -> Endpoint:
        """Start a container in *beside*'s network namespace (its addresses, routes and
        tunnel): a process that must be reachable where *beside* is, from another image.
        """
        name = self.container_name(role)
        argv = ["run", "-d", "--name", name, *self.labels, "--network",
                f"container:{beside.name}"]
        for mount in mounts:
            argv += ["-v", mount]
        self._docker(*argv, image, *command, what=f"start {role}")
        endpoint = Endpoint(name, beside.side, beside.ip)
        self.endpoints.append(endpoint)
        return endpoint

    def start_service(self, role: str, side: str, service: Mapping[str, Any],
                      volumes: Mapping[str, str | None]) -> Endpoint:
        """Start a compose *service* (:mod:`fleetctl.deploy.dockerrun`) on *side*.

        Every network the service names becomes *side*'s network; the run's labels, the
        alias *role* and ``NET_ADMIN`` (for the routes) are added.

        Args:
            volumes: The service's named volumes -> Docker volumes (``None``: anonymous).

        Raises:
            FleetError: the service cannot be converted, or the container did not start.
        """
        name = self.container_name(role)
        nets = service.get("networks") or []
        args = run_args(service, name=name, volumes=volumes,
                        networks={str(n): self.networks[side] for n in nets},
                        extra=[*self.labels, "--network-alias", role, "--cap-add", "NET_ADMIN"])
        self._docker("run", *args, what=f"start {role}")
        return self._attach(name, role, side)

    def container_name(self, role: str) -> str:
        """The name of the run's container *role*."""
        return f"fce2e-{self.run_id}-{role}"

    def _endpoint_args(self, role: str, side: str) -> list[str]:
        return [*self.labels, "--cap-add", "NET_ADMIN", "--network", self.networks[side],
                "--network-alias", role]

    def _attach(self, name: str, role: str, side: str) -> Endpoint:
        """Route the other side's subnet via the router, delete the default route."""
        other = SERVER_SIDE if side == ROBOT_SIDE else ROBOT_SIDE
        check(self.exec(name, ["ip", "route", "add", self.subnets[other], "via",
                               self.router_ips[side]]), f"route in {role}")
        check(self.exec(name, ["ip", "route", "del", "default"]), f"routes in {role}")
        info = json.loads(self._docker("inspect", name, what="inspect").stdout)[0]
        ip = info["NetworkSettings"]["Networks"][self.networks[side]]["IPAddress"]
        endpoint = Endpoint(name, side, ip)
        self.endpoints.append(endpoint)
        return endpoint

    def capabilities(self) -> Capabilities:
        """Which qdiscs the router's kernel offers (probed on its uplink interface)."""
        return detect(lambda argv: self.exec(self.router, argv),
                      self.router_devs[SERVER_SIDE])

    def shaper(self, direction: str, caps: Capabilities) -> LinkShaper:
        """The shaper of ``uplink`` (robot -> server) or ``downlink`` (server -> robot).

        Raises:
            FleetError: unknown direction.
        """
        sides = {"uplink": SERVER_SIDE, "downlink": ROBOT_SIDE}
        if direction not in sides:
            raise FleetError(f"direction must be uplink or downlink, not {direction!r}")
        return LinkShaper(lambda argv: self.exec(self.router, argv),
                          self.router_devs[sides[direction]], caps)

    def blackhole(self, side: str, on: bool) -> None:
        """Silently drop (or stop dropping) what the router forwards towards *side*.

        Two blackhole routes, one per half of the side's subnet, are more specific than the
        connected route, so the router discards forwarded packets without an ICMP answer,
        while ARP on that network goes on (see :class:`fleetctl.e2e.scenarios.Link`).

        Raises:
            FleetError: the route could not be changed.
        """
        net = ipaddress.ip_network(self.subnets[side])
        verb = "replace" if on else "del"
        for half in net.subnets(prefixlen_diff=1):
            res = self.exec(self.router, ["ip", "route", verb, "blackhole", str(half)])
            if on or "No such process" not in res.stderr:
                check(res, f"blackhole {half} {'on' if on else 'off'}")

    def blackhole_all(self, on: bool) -> int:
        """:meth:`blackhole` for both sides at once in the router; returns when the
        routes were all in place (or all gone), read by the router's own clock (ns since
        the epoch; containers share the host's clock).

        The time of a ``docker exec`` returning lags the change by 40-150 ms, more on a
        busy host: a restore mark taken on this side would make every recovery look that
        much shorter. Until 2026-11-29 the router ran one ``ip route`` per half and then
        ``date``, five process starts in a row: on a busy 2-core host the robot's frames
        crossed several milliseconds before the mark (a message published 6.7 ms before
        the restore mark counted as stale although it crossed after the first routes
        went). Now one ``ip -batch`` changes all four routes within microseconds and the
        clock is read in the process that ran it. That process is one agent kept for the
        run (:mod:`fleetctl.e2e.cutagent`), not a ``docker exec`` per cut, whose start-up
        and tear-down took the host's cores just when the stacks recovered.

        Raises:
            FleetError: a route could not be set, or one is still there after the removal.
        """
        halves = [str(h) for side in (SERVER_SIDE, ROBOT_SIDE)
                  for h in ipaddress.ip_network(self.subnets[side]).subnets(prefixlen_diff=1)]
        if self._cut_agent is None:  # close() ends it with the router
            self._cut_agent = CutAgent(self.router)
        mark, routes = self._cut_agent.change("replace" if on else "del", halves)
        left = [h for h in halves if h in routes.split()]
        if not on and left:
            raise FleetError(f"blackhole routes still in the router after the restore: {left}")
        return mark

    def tx_bytes(self, container: str, dev: str = "eth0") -> int:
        """Bytes *container* has sent on *dev* (from the kernel's counters)."""
        res = check(self.exec(container, ["cat", f"/sys/class/net/{dev}/statistics/tx_bytes"]),
                    "read tx_bytes")
        return int(res.stdout.strip())

    def count_tx(self, container: str, dev: str, seconds: float) -> TxWindow:
        """Bytes *container* sends on *dev* during the next *seconds*, timed inside it.

        The clock and the counter are read together in the container, at both ends of the
        window, so the window is *seconds* long to within a millisecond. Taking the time on
        this side of a ``docker exec`` instead adds the exec's start-up (60-90 ms idle, more
        on a busy host) to one end or the other: +-5% and more on a 2 s window.

        Raises:
            FleetError: the measurement failed.
        """
        res = check(self.exec(container, ["python3", "-c", _TX_WINDOW, dev, str(seconds)]),
                    f"count tx bytes of {dev}")
        start_ns, start_bytes, end_ns, end_bytes = (int(x) for x in res.stdout.split())
        return TxWindow(start_ns, end_ns, end_bytes - start_bytes)

    def running(self, container: str) -> bool:
        """Whether *container* exists and runs."""
        res = self.runner(["docker", "inspect", "-f", "{{.State.Running}}", container],
                          None, True)
        return res.returncode == 0 and res.stdout.strip() == "true"

    def mtu(self, container: str, dev: str) -> int:
        """The MTU of *dev* in *container* (bytes)."""
        res = check(self.exec(container, ["cat", f"/sys/class/net/{dev}/mtu"]), "read mtu")
        return int(res.stdout.strip())

    def logs(self, container: str) -> str:
        """The container's output so far (stdout and stderr)."""
        res = self.runner(["docker", "logs", container], None, True)
        return res.stdout + res.stderr

    def close(self) -> None:
        """Remove every container and network of this run (best effort, never raises).

        A signal that arrives meanwhile is raised when the removal is done.
        """
        with deferred():
            if self._cut_agent is not None:
                self._cut_agent.close()
                self._cut_agent = None
            names = [e.name for e in self.endpoints] + ([self.router] if self.router else [])
            runner = self.cleanup_runner or self.runner
            if names:
                # -v: anonymous volumes (the server's data) go with their containers.
                runner(["docker", "rm", "-f", "-v", *names], None, True)
            for net in self.networks.values():
                runner(["docker", "network", "rm", net], None, True)
            # What was made but not yet recorded (a `docker run` cut short by a signal).
            with contextlib.suppress(FleetError):
                cleanup.remove_run(runner, self.run_id)
            self.endpoints.clear()
            self.networks.clear()
            self.router = ""

    def __enter__(self) -> Topology:
        try:
            self.create()
        except BaseException:  # __exit__ does not run when __enter__ raises
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
