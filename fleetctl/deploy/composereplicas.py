"""The compose services and files of ``fleetctl up --replicas N`` (the layout and why:
:mod:`fleetctl.deploy.replicas`).

Pure rendering (:func:`services`, :func:`relay_config`, :func:`robot_client_config`) and
the files :func:`write_files` puts under ``FLEET/.compose``:

- ``server/relay-i.yaml``: replica *i*'s server.yaml (container paths, its ports, the
  ``cluster:`` section with its NATS user);
- ``secrets/relay-i/``: its TLS key and NATS password (0600; the entrypoint hands them to
  the unprivileged server process);
- ``nats/nats-k/nats.conf``: a NATS node's config (bcrypt hashes only), handed over the
  same way;
- ``robots/NAME/client.yaml``: a simulated robot's config with every replica's URL.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from fleetctl.deploy import replicas
from fleetctl.deploy.compose import (
    FLEET_ETC,
    RUN_ETC,
    SECRETS_ETC,
    SECRETS_RUN,
    SERVER_DATA,
    SERVER_WG_CONF,
    ComposePlan,
    _merge,
    _static,
    _wireguard,
    container_server_config,
)
from fleetctl.deploy.images import image_tag
from fleetctl.deploy.render import replica_urls
from fleetctl.errors import ConfigError
from fleetctl.smallfile import MAX_PEM_BYTES, read_small_text
from fleetctl.yamlfile import read_yaml

Write = Callable[..., None]
"""``compose._write(path, text, secret=...)``."""

_HEALTH_INTERVAL = {"interval": "2s", "timeout": "3s", "retries": 30}


def relay_ports(plan: ComposePlan, index: int) -> tuple[int, int]:
    """Replica *index*'s (from 0) plain and HTTPS ports inside the shared namespace."""
    return plan.server_port + index, plan.https_port + index


def robot_urls(plan: ComposePlan) -> list[str]:
    """Every replica's WebSocket URL as robots reach it (through the tunnel)."""
    return replica_urls(plan.server_ip, relay_ports(plan, 0)[0], plan.options.replicas)


def page_urls(plan: ComposePlan) -> list[str]:
    """Every replica's page on the server host."""
    return [plan.page_url(plan.published_https_port + i) for i in range(plan.options.replicas)]


def volumes(plan: ComposePlan) -> list[str]:
    """The named volumes: each replica's database, each NATS node's JetStream store."""
    return ([f"{name}-data" for name in replicas.replica_names(plan.options.replicas)]
            + [f"{node}-data" for node in replicas.NATS_NODES])


def services(plan: ComposePlan) -> dict[str, Any]:
    """The gateway (named ``server``), the relay replicas and the NATS nodes."""
    out: dict[str, Any] = {"server": _gateway(plan)}
    for index, name in enumerate(replicas.replica_names(plan.options.replicas)):
        out[name] = _relay(plan, index, name)
    static = replicas.nats_static_ips(plan.fleet_subnet)
    for node in replicas.NATS_NODES:
        out[node] = _nats(plan, node, static[node])
    return out


def _gateway(plan: ComposePlan) -> dict[str, Any]:
    bind = plan.published_bind
    ports = [f"{bind}:{plan.published_https_port + i}:{relay_ports(plan, i)[1]}/tcp"
             for i in range(plan.options.replicas)]
    if plan.wireguard:
        ports.append(f"{bind}:{plan.wireguard_port}:{plan.wireguard_port}/udp")
    health = ("import os, sys; sys.exit(0 if os.path.isdir('/sys/class/net/wg0') else 1)"
              if plan.wireguard else "pass")
    svc: dict[str, Any] = {
        "image": image_tag("server", plan.options.version),
        "command": ["python3", "-c", replicas.WAIT_FOR_STOP],
        "user": "root",  # the entrypoint brings WireGuard up, then drops privileges
        "volumes": [f"{plan.fleet_dir / 'server'}:{FLEET_ETC}:ro"],
        # `fleetctl status` asks the first replica that answers for the robot list.
        "environment": {"FLEETCTL_HEALTH": " ".join(
            f"http://127.0.0.1:{relay_ports(plan, i)[0]}/healthz"
            for i in range(plan.options.replicas))},
        "healthcheck": {"test": ["CMD", "python3", "-c", health], **_HEALTH_INTERVAL},
        "ports": ports,
        "restart": "unless-stopped",
        "networks": _static(plan, plan.server_ip),
    }
    return _merge(svc, _wireguard(SERVER_WG_CONF)) if plan.wireguard else svc


def _relay(plan: ComposePlan, index: int, name: str) -> dict[str, Any]:
    port = relay_ports(plan, index)[0]
    return {
        "image": image_tag("server", plan.options.version),
        "command": ["fleetctl", "server", "--config", f"{RUN_ETC}/{name}.yaml"],
        "user": "root",  # only until the entrypoint handed over the secrets
        "volumes": [
            f"{plan.compose_dir / 'server'}:{RUN_ETC}:ro",
            f"{plan.fleet_dir / 'server'}:{FLEET_ETC}:ro",
            f"{plan.compose_dir / 'secrets' / name}:{SECRETS_ETC}:ro",
            f"{name}-data:{SERVER_DATA}",
        ],
        "environment": {"FLEETCTL_HEALTH": f"http://127.0.0.1:{port}/healthz",
                        "FLEETCTL_SECRETS": SECRETS_ETC},
        "network_mode": "service:server",
        "depends_on": {"server": {"condition": "service_healthy"},
                       **{n: {"condition": "service_healthy"} for n in replicas.NATS_NODES}},
        "restart": "unless-stopped",
    }


def _nats(plan: ComposePlan, node: str, static_ip: str) -> dict[str, Any]:
    return {
        "image": image_tag("server", plan.options.version),
        "command": ["nats-server", "-c", f"{SECRETS_RUN}/{replicas.NATS_CONF}"],
        "user": "root",  # only until the entrypoint handed over the config
        "volumes": [f"{plan.compose_dir / 'nats' / node}:{SECRETS_ETC}:ro",
                    f"{node}-data:{replicas.NATS_DATA}"],
        "environment": {"FLEETCTL_SECRETS": SECRETS_ETC},
        "healthcheck": {"test": ["CMD", *replicas.NATS_HEALTH_COMMAND], **_HEALTH_INTERVAL},
        "restart": "unless-stopped",
        "networks": _static(plan, static_ip),
    }


def relay_config(plan: ComposePlan, index: int, name: str) -> dict[str, Any]:
    """Replica *name*'s server.yaml (pure)."""
    cfg = container_server_config(plan)
    port, https = relay_ports(plan, index)
    cfg["listen_port"] = port
    # The page fails over to the other replicas' ports on the host name it was opened by.
    cfg["web"] = {**cfg["web"], "listen_port": https, "replica_ports": [
        plan.published_https_port + i for i in range(plan.options.replicas)]}
    cfg["cluster"] = {
        "name": name,
        "nats_urls": replicas.nats_urls(index),
        "credentials": {"user": name,
                        "password_file": f"{SECRETS_RUN}/{replicas.PASSWORD_FILE}"},
        "subject_prefix": replicas.SUBJECT_PREFIX,
        "state_replicas": len(replicas.NATS_NODES),
    }
    return cfg


def robot_client_config(plan: ComposePlan, robot_dir: Path) -> str:
    """The robot's client.yaml with ``server_url`` listing every replica (pure but for
    reading the file).

    Raises:
        ConfigError: client.yaml is missing or not a mapping.
    """
    path = robot_dir / "client.yaml"
    data = read_yaml(path, "client config")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    data["server_url"] = robot_urls(plan)
    return yaml.safe_dump(data, sort_keys=False)


def write_files(plan: ComposePlan, write: Write) -> None:
    """Write the replicas' configs and secrets, the NATS configs and the simulated robots'
    configs under ``FLEET/.compose`` (secrets 0600, never through a link)."""
    out = plan.compose_dir
    key = read_small_text(plan.tls_key, MAX_PEM_BYTES)
    hashes: dict[str, str] = {}
    for index, name in enumerate(replicas.replica_names(plan.options.replicas)):
        write(out / "server" / f"{name}.yaml",
              yaml.safe_dump(relay_config(plan, index, name), sort_keys=False))
        secret_dir = out / "secrets" / name
        password = replicas.read_or_make_password(secret_dir / replicas.PASSWORD_FILE)
        write(secret_dir / replicas.PASSWORD_FILE, password + "\n", secret=True)
        write(secret_dir / "tls.key", key, secret=True)
        hashes[name] = replicas.password_hash(password)
    for node in replicas.NATS_NODES:
        write(out / "nats" / node / replicas.NATS_CONF, replicas.nats_config(node, hashes),
              secret=True)
    if plan.options.sim:
        for robot in plan.robots:
            write(out / "robots" / robot.name / "client.yaml",
                  robot_client_config(plan, robot.robot_dir))
