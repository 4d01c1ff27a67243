"""The fleet in the e2e topology: server, robot (client + load publisher), consumers.

One :class:`FleetRun` per ``fleetctl e2e`` invocation. It writes the server's config and
auth map (docs/design.md sections 3 and 4) into a work directory mounted at ``/e2e`` in every
container, starts components with :class:`~fleetctl.e2e.topology.Topology`, and reads the
consumers' sample files back. Every wait is a poll of a condition with a deadline.

Identities: the robot by its source address; consumers by a Bearer token whose SHA-256 is in
the auth map. With WireGuard (:mod:`fleetctl.e2e.wireguard`, as ``fleetctl up`` deploys a
fleet) robots reach the server through the tunnel and the robot is its VPN address; without,
the robot is the robot network's CIDR (routed, not NATed, through the router, so the server
sees the robot container's own address). Consumers always use the server network directly.
"""

from __future__ import annotations

import json
import secrets
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from fleetctl.deploy.images import image_tag
from fleetctl.e2e import profiles
from fleetctl.e2e.samples import Sample, load
from fleetctl.e2e.topology import IDLE_COMMAND, ROBOT_SIDE, SERVER_SIDE, Endpoint, Topology
from fleetctl.e2e.wireguard import TUN_DEVICE, Tunnel
from fleetctl.errors import FleetError
from fleetctl.tokens import hash_token
from fleetctl.waiting import wait_until

CONTAINER_DIR = "/e2e"
SERVER_PORT = 8080
_SITE = "/opt/fleetctl/lib/python3.11/site-packages/fleetctl"
_POLL_S = 0.1
_HEALTH = ("import urllib.request; urllib.request.urlopen("
           f"'http://127.0.0.1:{SERVER_PORT}/healthz', timeout=1)")


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
        source_dir: A source tree whose ``fleetctl/`` package is mounted over the images'
            (development: test code changes without ``fleetctl build``); None uses the
            images as built.
        tunnel: Run server and robots over this WireGuard tunnel; None: the routed
            network only.
    """

    topo: Topology
    work: Path
    source_dir: Path | None = None
    tunnel: Tunnel | None = None
    token: str = field(default_factory=lambda: secrets.token_urlsafe(24), repr=False)
    server: Endpoint | None = None
    wg_ifaces: dict[str, str] = field(default_factory=dict)  # robot container -> interface

    @property
    def out(self) -> Path:
        """Host side of ``/e2e/out`` (sample files)."""
        return self.work / "out"

    @property
    def server_url(self) -> str:
        """The server's WebSocket URL as robots and consumers reach it."""
        if self.server is None:
            raise FleetError("the server is not started")
        return f"ws://{self.server.ip}:{SERVER_PORT}/"

    @property
    def robot_server_url(self) -> str:
        """The server's URL as robots reach it (through the tunnel, when there is one)."""
        if self.tunnel is None:
            return self.server_url
        return self.tunnel.server_url(SERVER_PORT)

    def mounts(self) -> list[str]:
        """``-v`` specifications every fleet container gets."""
        mounts = [f"{self.work}:{CONTAINER_DIR}"]
        if self.source_dir is not None:
            mounts.append(f"{self.source_dir / 'fleetctl'}:{_SITE}:ro")
        return mounts

    def write_configs(self) -> None:
        """Write ``server.yaml``, ``auth.yaml`` and the consumers' token file."""
        self.out.mkdir(parents=True, exist_ok=True)
        for path in (self.work, self.out):
            path.chmod(0o777)
        robot: dict[str, str] = ({"ip": self.tunnel.robot_vpn_ip} if self.tunnel
                                 else {"cidr": self.topo.subnets[ROBOT_SIDE]})
        auth = {"version": 1, "identities": [
            {"name": profiles.ROBOT, **robot,
             "rules": [{"topic": f"/{profiles.ROBOT}/.*", "op": "send"}]},
            {"name": "e2e-consumer",
             "token_sha256": hash_token(self.token),
             "rules": [{"topic": ".*", "op": "receive"}]},
        ]}
        server = {"listen_host": "0.0.0.0", "listen_port": SERVER_PORT,
                  "auth_map": "auth.yaml", "database": None}
        (self.work / "auth.yaml").write_text(yaml.safe_dump(auth, sort_keys=False))
        (self.work / "server.yaml").write_text(yaml.safe_dump(server, sort_keys=False))
        token_file = self.work / "token"
        token_file.write_text(self.token)
        token_file.chmod(0o644)  # the consumers run as another user; the token is a test's

    def start_server(self) -> Endpoint:
        """Start ``fleetctl server`` and wait until ``/healthz`` answers.

        With a tunnel, the server's WireGuard is up first, and the robots' ``Endpoint`` is
        set to the server container's address.

        Raises:
            FleetError: the server container stopped, or did not answer in time.
        """
        if self.tunnel is not None:
            self.tunnel.create([self.topo.subnets[ROBOT_SIDE], self.topo.subnets[SERVER_SIDE]])
        self.write_configs()
        self.server = self.topo.start(
            "server", SERVER_SIDE, image_tag("server"),
            ["fleetctl", "server", "--config", f"{CONTAINER_DIR}/server.yaml"],
            mounts=self.mounts(),
            **self._wireguard(self.tunnel.server_iface if self.tunnel else None))
        if self.tunnel is not None:
            self.tunnel.set_endpoint(self.server.ip)
        name = self.server.name
        self.wait_healthy(name, "the server's /healthz", lambda: self.topo.exec(
            name, ["python3", "-c", _HEALTH]).returncode == 0, 30.0)
        return self.server

    def _wireguard(self, iface: str | None) -> dict[str, Any]:
        """``Topology.start`` arguments that bring *iface* up in the container (or none)."""
        if self.tunnel is None or iface is None:
            return {}
        # The entrypoint needs root, NET_ADMIN (every e2e container has it) and the TUN
        # device for wireguard-go; it drops to the fleetctl user before the command runs.
        return {"env": self.tunnel.container_env(iface), "user": "root",
                "devices": [str(TUN_DEVICE)]}

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
                    load_profile: str) -> Endpoint:
        """Start a robot: the load publisher and ``fleetctl client`` in one container.

        Args:
            role: Container role (also names its config and published file).
            client_profile: What the client config says (the baseline's differs).
            load_profile: Profile name the load publisher publishes.
        """
        cfg = profiles.client_config(client_profile, self.robot_server_url)
        (self.work / f"{role}.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
        script = (f"python3 -m fleetctl.e2e.load --profile {load_profile} "
                  f"--out {CONTAINER_DIR}/out/{role}-published.json & "
                  "echo $! > /tmp/load.pid; "
                  f"exec fleetctl client --config {CONTAINER_DIR}/{role}.yaml")
        iface = self.tunnel.robot_iface() if self.tunnel else None
        wg = self._wireguard(iface)
        env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", **wg.pop("env", {})}
        robot = self.topo.start(role, ROBOT_SIDE, image_tag("client"), ["bash", "-c", script],
                                env=env, mounts=self.mounts(), **wg)
        if iface is not None:
            self.wg_ifaces[robot.name] = iface
        return robot

    def latest_handshake_ns(self, robot: Endpoint) -> int | None:
        """When *robot*'s WireGuard last completed a handshake (ns since the epoch, one
        second resolution); None without a tunnel or before the first handshake."""
        iface = self.wg_ifaces.get(robot.name)
        if iface is None:
            return None
        res = self.topo.exec(robot.name, ["wg", "show", iface, "latest-handshakes"])
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

    def start_consumers(self, role: str, count: int, regex: str = ".*") -> Endpoint:
        """Start *count* WebSocket consumers in one container; wait until all subscribed."""
        ep = self.topo.start(
            role, SERVER_SIDE, image_tag("server"),
            ["python3", "-m", "fleetctl.e2e.consumer", "--url", self.server_url,
             "--token-file", f"{CONTAINER_DIR}/token", "--subscribe", regex,
             "--count", str(count), "--name", role, "--out", f"{CONTAINER_DIR}/out"],
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
        self.topo.runner(["docker", "rm", "-f", *names], None, True)
        self.topo.endpoints[:] = [e for e in self.topo.endpoints if e.name not in names]

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
