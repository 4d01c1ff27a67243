"""Before ``fleetctl up``: are the host ports the compose file publishes free?

Compose only finds out that a port is taken once it starts the container, and then prints
docker's "driver failed programming external connectivity ... bind: address already in
use" and leaves a created, stopped server behind. Checking first turns that into one line
that names the port and the setting that chose it.

A port that this fleet's own running containers already publish is not in the way: ``up``
on a running fleet re-applies the same ports.
"""

from __future__ import annotations

import errno
import re
import socket
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from fleetctl.deploy.dockercli import CONFIG_FILES_LABEL, Runner
from fleetctl.errors import ConflictError


@dataclass(frozen=True)
class PublishedPort:
    """One ``ports:`` entry of a compose service: host address, host port, protocol."""

    service: str
    host: str  # as compose has it: an IPv6 address in brackets
    port: int
    protocol: str  # "tcp" | "udp"


# compose's long form is never written by fleetctl; this is its "HOST:PORT:PORT/PROTO".
_ENTRY = re.compile(r"^(?P<host>\[[^\]]+\]|[^:\[\]]+):(?P<port>\d+):\d+(?:/(?P<proto>tcp|udp))?$")
# `docker ps --format '{{.Ports}}'`: "0.0.0.0:8443->8443/tcp, [::]:51820->51820/udp"
_DOCKER_PS = re.compile(r":(?P<port>\d+)->\d+/(?P<proto>tcp|udp)")


def published_ports(document: dict[str, Any]) -> list[PublishedPort]:
    """Every host port the compose *document* (``compose.render``) publishes."""
    found = []
    for service, spec in (document.get("services") or {}).items():
        for entry in spec.get("ports") or ():
            match = _ENTRY.match(str(entry))
            if match is None:  # not fleetctl's own short form: compose will judge it
                continue
            found.append(PublishedPort(service, match["host"], int(match["port"]),
                                       match["proto"] or "tcp"))
    return found


def held_by_fleet(runner: Runner, project: str,
                  is_ours: Callable[[str], bool]) -> set[tuple[int, str]]:
    """(port, protocol) pairs that the running containers of this fleet publish.

    Only the containers of *project* whose compose file (compose's config-files label)
    *is_ours* accepts: a container of the same project name from another fleet
    directory is "another program" to this fleet, while one made from this directory's
    file before it was moved is this fleet's (``up`` recreates it from the new place).
    """
    res = runner(["docker", "ps", "--filter", f"label=com.docker.compose.project={project}",
                  "--format", f'{{{{.Label "{CONFIG_FILES_LABEL}"}}}}\t{{{{.Ports}}}}'],
                 None, True)
    if res.returncode != 0:
        return set()
    held = set()
    for line in res.stdout.splitlines():
        made_from, _, ports = line.partition("\t")
        if made_from.strip() and is_ours(made_from.strip()):
            held |= {(int(m["port"]), m["proto"]) for m in _DOCKER_PS.finditer(ports)}
    return held


def bind_error(host: str, port: int, protocol: str) -> OSError | None:
    """The error binding *host*:*port*/*protocol* on this host gives, or ``None`` if free."""
    address = host[1:-1] if host.startswith("[") else host
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    kind = socket.SOCK_STREAM if protocol == "tcp" else socket.SOCK_DGRAM
    with socket.socket(family, kind) as probe:
        if kind == socket.SOCK_STREAM:
            # A listener's old connections in TIME_WAIT do not stop docker's bind either.
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((address, port))
        except OSError as exc:
            return exc
    return None


def _setting(port: PublishedPort) -> str:
    if port.protocol == "udp":
        return "wireguard_port in fleet.yaml (then `fleetctl set-endpoint`)"
    return "`fleetctl up --https-port PORT`, or https_port in fleet.yaml"


def _reason(exc: OSError) -> str:
    if exc.errno == errno.EADDRINUSE:
        return "is in use by another program"
    if exc.errno == errno.EADDRNOTAVAIL:
        return "cannot be bound: the address is not one of this host's (`--bind`)"
    if exc.errno == errno.EACCES:
        return "cannot be bound: permission denied"
    return f"cannot be bound: {exc.strerror or exc}"


PortProbe = Callable[[str, int, str], "OSError | None"]


def require_free(ports: Iterable[PublishedPort], held: set[tuple[int, str]],
                 probe: PortProbe = bind_error) -> None:
    """Raise a :class:`ConflictError` naming every port that compose could not publish.

    Raises:
        ConflictError: a port is taken (or its address is not this host's).
    """
    problems = []
    for port in ports:
        if (port.port, port.protocol) in held:
            continue
        exc = probe(port.host, port.port, port.protocol)
        if exc is not None:
            problems.append(f"{port.host}:{port.port}/{port.protocol} ({port.service}) "
                            f"{_reason(exc)}; change it with {_setting(port)}")
    if problems:
        raise ConflictError("cannot start the fleet: " + "; ".join(problems))
