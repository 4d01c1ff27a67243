"""The fleet in the e2e topology: server, robot (client + load publisher), consumers.

One :class:`FleetRun` per ``fleetctl e2e`` invocation. The server is the container
``fleetctl up`` deploys, from ``up``'s own files (:mod:`fleetctl.e2e.deployment`); robots and
consumers get their configs from a work directory mounted at ``/e2e``. Components are
started with :class:`~fleetctl.e2e.topology.Topology`; the consumers' sample files are read
back. Every wait is a poll of a condition with a deadline.

Identities: the robot by its source address; consumers by the fleet's viewer token. With
WireGuard robots reach the server's plain listener through the tunnel and the robot is its
fleet address; without, the robot is the robot network's CIDR (routed, not NATed, through
the router, so the server sees the robot container's own address). Consumers reach the
HTTPS listener on the server network, as people do.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from fleetctl.deploy.images import image_tag
from fleetctl.e2e import profiles
from fleetctl.e2e.deployment import SERVER_ALIAS, SITE_PACKAGE, WG_IFACE, Deployment
from fleetctl.e2e.samples import Sample, load
from fleetctl.e2e.topology import IDLE_COMMAND, ROBOT_SIDE, SERVER_SIDE, Endpoint, Topology
from fleetctl.errors import FleetError
from fleetctl.waiting import wait_until

CONTAINER_DIR = "/e2e"
_POLL_S = 0.1
# The image's own HEALTHCHECK (FLEETCTL_HEALTH comes from `up`'s service definition).
_HEALTH = ["python3", "/usr/local/bin/fleetctl-healthcheck"]


def wait_for(what: str, condition: Callable[[], bool], timeout_s: float) -> None:
    """Poll *condition* until true.

    Raises:
        FleetError: still false after *timeout_s* seconds (names *what*).
    """
    wait_until(condition, timeout_s, _POLL_S, describe=what)


def hold(seconds: float) -> None:
    """Let the experiment run for *seconds* (a measured phase of the timeline)."""
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        time.sleep(min(left, _POLL_S))


@dataclass
class FleetRun:
    """Server and helpers of one invocation.

    Args:
        topo: The topology (networks and router already up).
        work: Host directory mounted at ``/e2e`` (made world-writable: the images run as
            an unprivileged user).
        deployment: The fleet as ``up`` deploys it (its ``work`` is this *work*; its
            ``source_dir``, when set, is mounted over the images' package in every
            container: development without ``fleetctl build``).
    """

    topo: Topology
    work: Path
    deployment: Deployment
    images: dict[str, str] = field(default_factory=dict)  # name -> image pinned by id
    server: Endpoint | None = None
    tunnelled: set[str] = field(default_factory=set)  # robot containers with WireGuard

    def image(self, name: str) -> str:
        """The image of component *name* (``server``, ``client``): pinned to its id at the
        run's start when :meth:`pin_images` ran, so a concurrent ``fleetctl build`` that
        retags the images cannot change them in the middle of a run."""
        return self.images.get(name) or image_tag(name)

    def pin_images(self, *names: str) -> None:
        """Resolve each image tag to its id now (an unresolvable tag stays a tag)."""
        for name in names:
            res = self.topo.runner(["docker", "image", "inspect", "-f", "{{.Id}}",
                                    image_tag(name)], None, True)
            if res.returncode == 0 and res.stdout.strip():
                self.images[name] = res.stdout.strip()

    @property
    def wireguard(self) -> bool:
        """Whether robots reach the server through WireGuard."""
        return self.deployment.wireguard

    @property
    def source_dir(self) -> Path | None:
        """The checkout mounted over the images' package, if any."""
        return self.deployment.source_dir

    @property
    def out(self) -> Path:
        """Host side of ``/e2e/out`` (sample files)."""
        return self.work / "out"

    @property
    def server_ip(self) -> str:
        """The server container's address on the server network.

        Raises:
            FleetError: the server is not started.
        """
        if self.server is None:
            raise FleetError("the server is not started")
        return self.server.ip

    @property
    def server_url(self) -> str:
        """The ``wss://`` URL consumers use (the HTTPS listener)."""
        return self.deployment.consumer_url(self.server_ip)

    @property
    def robot_server_url(self) -> str:
        """The ``ws://`` URL robots use (through the tunnel, when there is one)."""
        return self.deployment.robot_url(self.server_ip)

    def mounts(self) -> list[str]:
        """``-v`` specifications every fleet container gets."""
        mounts = [f"{self.work}:{CONTAINER_DIR}"]
        if self.source_dir is not None:
            mounts.append(f"{self.source_dir / 'fleetctl'}:{SITE_PACKAGE}:ro")
        return mounts

    def prepare(self) -> None:
        """Make the work directories (world-writable: the images run unprivileged)."""
        self.out.mkdir(parents=True, exist_ok=True)
        for path in (self.work, self.out):
            path.chmod(0o777)

    def start_server(self) -> Endpoint:
        """Start ``up``'s server container and wait until its health check passes.

        Raises:
            FleetError: the server container stopped, or did not answer in time.
        """
        self.prepare()
        subnets = self.topo.subnets
        self.deployment.create([subnets[ROBOT_SIDE], subnets[SERVER_SIDE]], subnets[ROBOT_SIDE])
        service = self.deployment.server_service()
        service["image"] = self.image("server")  # up's image, pinned (see image())
        self.server = self.topo.start_service(SERVER_ALIAS, SERVER_SIDE, service,
                                              {"server-data": None})
        name = self.server.name
        self.wait_healthy(name, "the server's health check", lambda: self.topo.exec(
            name, _HEALTH).returncode == 0, 30.0)
        return self.server

    def wait_healthy(self, name: str, what: str, condition: Callable[[], bool],
                     timeout_s: float) -> None:
        """Wait for *condition*; fail at once (with the container's log) if *name* stops.

        Raises:
            FleetError: the container stopped, or the deadline passed.
        """
        def ready() -> bool:
            if condition():
                return True
            if not self.topo.running(name):
                raise FleetError(f"{name} stopped while waiting for {what}: "
                                 f"{self.topo.logs(name)[-800:]}")
            return False

        try:
            wait_for(what, ready, timeout_s)
        except FleetError as exc:
            if "stopped while" in str(exc):
                raise
            raise FleetError(f"{exc}; log of {name}: {self.topo.logs(name)[-800:]}") from exc

    def start_robot(self, role: str, client_profile: profiles.Profile,
                    load_profile: str, relay_command: str | None = None,
                    server_urls: list[str] | None = None) -> Endpoint:
        """Start a robot: the load publisher and ``fleetctl client`` in one container.

        Args:
            role: Container role (also names its config and published file).
            client_profile: What the client config says (the baseline's differs).
            load_profile: Profile name the load publisher publishes.
            relay_command: What carries the load instead of ``fleetctl client`` (a peer's
                bridge, shell words); None: the client with *client_profile*'s config.
            server_urls: Relay replicas' ``ws://`` URLs on the routed network (the client
                fails over between them); None: the run's server, through the tunnel when
                there is one.
        """
        if relay_command is None:
            url: str | list[str] = server_urls or self.robot_server_url
            cfg = profiles.client_config(client_profile, url)
            (self.work / f"{role}.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
            relay_command = f"fleetctl client --config {CONTAINER_DIR}/{role}.yaml"
        script = (f"python3 -m fleetctl.e2e.load --profile {load_profile} "
                  f"--out {CONTAINER_DIR}/out/{role}-published.json & "
                  f"echo $! > /tmp/load.pid; exec {relay_command}")
        wg = {} if server_urls else self.deployment.robot_options(self.server_ip)
        env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", **wg.pop("env", {})}
        mounts = [*self.mounts(), *wg.pop("mounts", [])]
        robot = self.topo.start(role, ROBOT_SIDE, self.image("client"), ["bash", "-c", script],
                                env=env, mounts=mounts, **wg)
        if self.wireguard and not server_urls:
            self.tunnelled.add(robot.name)
        return robot

    def latest_handshake_ns(self, robot: Endpoint) -> int | None:
        """When *robot*'s WireGuard last completed a handshake (ns since the epoch, one
        second resolution); None without a tunnel or before the first handshake."""
        if robot.name not in self.tunnelled:
            return None
        res = self.topo.exec(robot.name, ["wg", "show", WG_IFACE, "latest-handshakes"])
        fields = res.stdout.split()
        if res.returncode != 0 or len(fields) < 2 or not fields[1].isdigit():
            return None
        return int(fields[1]) * 1_000_000_000 or None

    def stop_load(self, robot: Endpoint, role: str) -> dict[str, dict[str, int]]:
        """Stop the robot's load publisher; returns what it published per wire topic."""
        self.topo.exec(robot.name, ["bash", "-c", "kill -TERM $(cat /tmp/load.pid)"])
        path = self.out / f"{role}-published.json"
        wait_for(f"{path.name}", path.is_file, 15.0)
        wait_for(f"{path.name} written", lambda: path.stat().st_size > 0, 5.0)
        data: dict[str, dict[str, int]] = json.loads(path.read_text())
        return data

    def start_consumers(self, role: str, count: int, regex: str = ".*",
                        image: str = "server", url: str | list[str] | None = None,
                        session: str | None = None,
                        beside_server: bool = False) -> Endpoint:
        """Start *count* WebSocket consumers in one container; wait until all subscribed.

        *image* is the component image they run in: ``client`` where they must decode
        video (PyAV is in the client image only). *url*: another relay than the run's
        server (a replica's ``wss://`` URL), or a failover list of them. *session*: the
        consumers name sessions (``<session>-<i>``) and reconnect after a close.
        *beside_server*: the container shares the server's network namespace and reaches
        the relay's plain listener on loopback (the ``peer`` scenarios, where the other
        stack's consumer is placed the same way); otherwise it is a host of the server
        network on the HTTPS listener, as people are.
        """
        if beside_server:
            urls = [self.deployment.loopback_url()]
        else:
            urls = [url] if isinstance(url, str) else url or [self.server_url]
        args = ["python3", "-m", "fleetctl.e2e.consumer",
                *(a for u in urls for a in ("--url", u)),
                "--ca-file", f"{CONTAINER_DIR}/tls-cert.pem", "--tls-name", SERVER_ALIAS,
                "--token-file", f"{CONTAINER_DIR}/token", "--subscribe", regex,
                "--count", str(count), "--name", role, "--out", f"{CONTAINER_DIR}/out"]
        if session is not None:
            args += ["--session", session]
        if beside_server:
            if self.server is None:
                raise FleetError("the server is not started")
            ep = self.topo.start_beside(role, self.server, self.image(image), args,
                                        mounts=self.mounts())
        else:
            ep = self.topo.start(role, SERVER_SIDE, self.image(image), args,
                                 mounts=self.mounts())
        ready = [self.out / f"{role}-{i}.ready" for i in range(count)]
        try:
            wait_for(f"{count} consumer(s) {role} subscribed",
                     lambda: all(p.exists() for p in ready), 30.0)
        except FleetError as exc:
            raise FleetError(f"{exc}; consumer log: {self.topo.logs(ep.name)[-500:]}") from exc
        return ep

    def remove(self, *endpoints: Endpoint) -> None:
        """Stop and remove containers of this run (their files stay in the work dir)."""
        names = [e.name for e in endpoints]
        self.keep_logs(names)
        self.topo.runner(["docker", "rm", "-f", "-v", *names], None, True)
        self.topo.endpoints[:] = [e for e in self.topo.endpoints if e.name not in names]

    def keep_logs(self, names: Iterable[str]) -> None:
        """Write each container's output to ``<work>/logs/<role>.log`` before it goes: a
        failed criterion is explained by the client's reconnects and the server's log."""
        logs = self.work / "logs"
        logs.mkdir(exist_ok=True)
        for name in names:
            role = name.removeprefix(f"fce2e-{self.topo.run_id}-")
            res = self.topo.runner(["docker", "logs", "--timestamps", name], None, True)
            (logs / f"{role}.log").write_text(res.stdout + res.stderr)

    def samples(self, prefix: str) -> list[Sample]:
        """Every sample written by consumers whose name starts with *prefix*."""
        out: list[Sample] = []
        for path in sorted(self.out.glob(f"{prefix}-*.jsonl")):
            text = path.read_text()
            # A line may be half-written while consumers run: parse whole lines only.
            out.extend(load(text[: text.rfind("\n") + 1], str(path)))
        return out

    def wait_flowing(self, prefix: str, topics: Iterable[str], consumers: Sequence[str],
                     timeout_s: float = 60.0) -> None:
        """Wait until every consumer in *consumers* got each of *topics* at least once."""
        want = {(c, t) for c in consumers for t in topics}

        def flowing() -> bool:
            return want <= {(s.consumer, s.topic) for s in self.samples(prefix)}

        wait_for(f"messages of {sorted(set(topics))} at {len(consumers)} consumer(s)",
                 flowing, timeout_s)

    def start_idle(self, role: str, side: str, image: str,
                   env: dict[str, str] | None = None) -> Endpoint:
        """A container that waits (commands are run in it with ``docker exec``)."""
        return self.topo.start(role, side, image, IDLE_COMMAND, env=env, mounts=self.mounts())
