"""``fleetctl up --replicas N``: N relay replicas on a 3-node NATS cluster (issue 15).

What runs (docs/scaling.md, "Deploying replicas"):

- ``server``: the fleet's network front, no relay. It holds the WireGuard tunnel (robots
  reach it exactly as they reach a single server: ``Endpoint = server:PORT``, the same keys)
  and publishes every replica's HTTPS port and the WireGuard port. It only waits.
- ``relay-1`` .. ``relay-N``: ``fleetctl server`` each, in the ``server`` container's network
  namespace (``network_mode: service:server``): every replica sees the robots' tunnel
  addresses, so the auth map's IP identities work unchanged, and one replica dying leaves
  the tunnel and the others up. Replica *i* listens on the fleet's port + *i* - 1 (plain
  ``ws://``, inside the tunnel and on loopback) and the HTTPS port + *i* - 1.
- ``nats-1`` .. ``nats-3``: a NATS cluster with JetStream (the shared robot registry and
  latched messages, three copies: ``state_replicas: 3``), from the server image (it carries
  ``nats-server``), its store on a volume per node.

Robots fail over with client-side URL lists (docs/client.md, "Replicas and failover"):
simulated robots get ``server_url: [ws://10.8.0.1:8080/, ws://10.8.0.1:8081/, ...]``;
robots on other hosts get it in their generated ``client.yaml`` once ``up --replicas N``
has recorded N in fleet.yaml (``relay_replicas``). No load balancer: the client's list
already does what HAProxy would, without another hop or a place that rewrites robots'
addresses.

Credentials: every replica has its own NATS user and a random password (32 bytes), kept in
``.compose/secrets/relay-i/nats.password`` (0600, reused by the next ``up``); the NATS
configs hold only bcrypt hashes. Each user may publish only on the fleet's subjects
(``<prefix>.>``), its two KV buckets and the JetStream API calls on them, and subscribe
only to ``<prefix>.>`` and its inboxes (:func:`nats_permissions`). The routes between NATS
nodes stay on the compose network, which publishes no NATS port.
"""

from __future__ import annotations

import ipaddress
import json
import secrets
from pathlib import Path
from typing import Any

import bcrypt

from fleetctl.deploy.fleet import MAX_RELAY_REPLICAS
from fleetctl.errors import ConfigError
from fleetctl.smallfile import MAX_SECRET_BYTES, read_small_text

NATS_NODES = ("nats-1", "nats-2", "nats-3")
NATS_CLIENT_PORT, NATS_ROUTE_PORT, NATS_MONITOR_PORT = 4222, 6222, 8222
NATS_HEALTH_COMMAND = [
    "python3", "-c",
    "import sys, urllib.request; sys.exit(0 if urllib.request.urlopen("
    f"'http://127.0.0.1:{NATS_MONITOR_PORT}/healthz', timeout=2).status == 200 else 1)"]
"""Exit 0 when the NATS node in this container is healthy (its monitoring endpoint; with
JetStream, once the cluster elected its meta leader): `up`'s and e2e's health check."""
MAX_REPLICAS = MAX_RELAY_REPLICAS
SUBJECT_PREFIX = "fleetctl"
# <prefix>_<name>: sharedregistry.py, sharedlatched.py, sharedsessions.py, remoteinterest.py
BUCKETS = ("robots", "latched", "sessions", "interest")
NODROP_STREAM = "nodrop"  # <prefix>_nodrop on subjects <prefix>_nd.>: sharedsessions.py
PASSWORD_FILE = "nats.password"
NATS_CONF = "nats.conf"
NATS_DATA = "/var/lib/fleetctl"  # owned by the image's fleetctl user, a volume per node
# bcrypt's cost: nats-server checks the hash once per connection, not per message.
BCRYPT_ROUNDS = 11
# The gateway waits for SIGTERM (docker stop) and exits; as PID 1 a process must block the
# signal and wait for it, or it is ignored.
WAIT_FOR_STOP = ("import signal; s = {signal.SIGTERM, signal.SIGINT}; "
                 "signal.pthread_sigmask(signal.SIG_BLOCK, s); signal.sigwait(s)")


def replica_names(count: int) -> list[str]:
    """``relay-1`` .. ``relay-<count>``."""
    return [f"relay-{i}" for i in range(1, count + 1)]


def check_count(count: int) -> int:
    """*count* if it is a replica count ``up`` can deploy.

    Raises:
        ConfigError: Not 1 .. :data:`MAX_REPLICAS` (names ``--replicas``).
    """
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_REPLICAS:
        raise ConfigError(f"--replicas {count!r}: expected 1 to {MAX_REPLICAS}")
    return count


def nats_permissions(prefix: str = SUBJECT_PREFIX) -> dict[str, Any]:
    """What one replica's NATS user may do: the fleet's subjects, its KV buckets, the
    sessions' no_drop stream and the JetStream API on them, nothing else (no stream
    delete or purge)."""
    streams = [f"KV_{prefix}_{b}" for b in BUCKETS] + [f"{prefix}_{NODROP_STREAM}"]
    publish = [f"{prefix}.>", f"{prefix}_nd.>", "$JS.API.INFO"]
    for stream in streams:
        if stream.startswith("KV_"):
            publish.append(f"$KV.{stream[3:]}.>")
        publish += [f"$JS.API.STREAM.INFO.{stream}",
                    f"$JS.API.STREAM.CREATE.{stream}", f"$JS.API.STREAM.UPDATE.{stream}",
                    f"$JS.API.CONSUMER.CREATE.{stream}", f"$JS.API.CONSUMER.CREATE.{stream}.>",
                    f"$JS.API.CONSUMER.DELETE.{stream}.>", f"$JS.API.CONSUMER.INFO.{stream}.>",
                    f"$JS.API.DIRECT.GET.{stream}", f"$JS.API.DIRECT.GET.{stream}.>",
                    f"$JS.API.STREAM.MSG.GET.{stream}", f"$JS.FC.{stream}.>"]
    return {"publish": {"allow": publish},
            "subscribe": {"allow": [f"{prefix}.>", "_INBOX.>"]}}


def password_hash(password: str) -> str:
    """The bcrypt hash nats-server checks *password* against."""
    return bcrypt.hashpw(password.encode(), bcrypt.gensalt(BCRYPT_ROUNDS)).decode()


def nats_config(node: str, users: dict[str, str]) -> str:
    """*node*'s ``nats-server`` config: JSON (which the NATS config format reads), so every
    value is escaped by ``json.dumps``. *users* maps replica names to bcrypt hashes."""
    if node not in NATS_NODES:
        raise ValueError(f"unknown NATS node {node!r}")
    routes = [f"nats://{n}:{NATS_ROUTE_PORT}" for n in NATS_NODES if n != node]
    config = {
        "server_name": node,
        "listen": f"0.0.0.0:{NATS_CLIENT_PORT}",
        "http": f"0.0.0.0:{NATS_MONITOR_PORT}",
        "jetstream": {"store_dir": f"{NATS_DATA}/jetstream"},
        "cluster": {"name": "fleet", "listen": f"0.0.0.0:{NATS_ROUTE_PORT}", "routes": routes},
        "authorization": {"users": [
            {"user": name, "password": digest, "permissions": nats_permissions()}
            for name, digest in sorted(users.items())]},
    }
    return json.dumps(config, indent=2) + "\n"


def nats_urls(index: int) -> list[str]:
    """The NATS URLs of replica *index* (from 0): all three nodes, starting with a
    different one per replica so that the replicas spread over the cluster."""
    start = index % len(NATS_NODES)
    order = NATS_NODES[start:] + NATS_NODES[:start]
    return [f"nats://{n}:{NATS_CLIENT_PORT}" for n in order]


def read_or_make_password(path: Path) -> str:
    """The replica's NATS password from *path* (never through a symlink), or a new random
    one when there is none yet (the caller writes it, 0600).

    Raises:
        ConfigError: *path* exists but cannot be read or is empty.
    """
    try:
        text = read_small_text(path, MAX_SECRET_BYTES, follow_symlinks=False).strip()
    except FileNotFoundError:
        return secrets.token_urlsafe(32)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the replica's NATS password: "
                          f"{exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: the replica's NATS password is not UTF-8 text") from None
    if not text:
        raise ConfigError(f"{path}: empty NATS password; delete it and run `fleetctl up`")
    return text


def nats_static_ips(fleet_subnet: str) -> dict[str, str]:
    """Plain mode (the compose network is the fleet subnet): fixed addresses for the NATS
    nodes at the top of the subnet, below docker's gateway (the last address) and far from
    the robots, which are numbered from the bottom."""
    top = ipaddress.ip_network(fleet_subnet).broadcast_address
    return {node: str(top - 2 - i) for i, node in enumerate(NATS_NODES)}
