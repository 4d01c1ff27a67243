"""Fleet changes applied to a running deployment, without restarting what did not change.

After ``add-robot``, ``remove-robot``, ``add-user``, ``remove-user``, ``render`` and
``set-endpoint`` the CLI calls :func:`sync_running`:

- **auth.yaml**: nothing to do here. The server watches the file (mounted live from
  ``FLEET/server``) and reloads it within a second; revoked connections are closed, the rest
  keep theirs.
- **WireGuard peers**: ``wg syncconf`` in the server container from the live
  ``FLEET/server/wireguard/wg0.conf``: new peers are added, removed ones dropped, and the
  sessions of unchanged peers are untouched (unlike ``wg setconf`` or a restart).
- **TLS certificate** (``set-endpoint`` makes a new self-signed one for the new name) and
  **server.yaml** (``render`` after fleet.yaml's ``recording:`` section changed): the
  container's copies are refreshed and the server restarted, as it loads both at start;
  robots reconnect by themselves.
- **simulated robots** (a deployment started with ``--sim``): the compose file is
  re-rendered and ``up`` creates the new robot's container (or removes a removed one's);
  the server and the other robots are not recreated, as their definitions did not change.
- **the server's own compose definition** (``render`` after fleet.yaml's ``https_port``,
  ``wireguard_port`` or ``server_port`` changed): a restart keeps the ports the container
  was created with, so the server listened on the new port behind the old mapping and the
  page was unreachable on both while ``status`` said healthy. The deployment is brought up
  to date as ``fleetctl up`` with its recorded options would (the new host ports are
  checked first; compose recreates only what changed).
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from pathlib import Path

import yaml

from fleetctl.deploy import composerun
from fleetctl.deploy.compose import (
    ROBOT_SERVICE_PREFIX,
    SERVER_WG_CONF,
    WG_INTERFACE,
    ComposePlan,
    plan_for,
    render,
    saved_options,
    server_config_text,
    write_files,
)
from fleetctl.deploy.dockercli import Runner, check, docker_unreachable, subprocess_runner
from fleetctl.deploy.replicas import replica_names
from fleetctl.errors import FleetError
from fleetctl.smallfile import MAX_CONFIG_BYTES, MAX_PEM_BYTES, read_small


def sync_running(fleet_dir: Path, progress: Callable[[str], None],
                 runner: Runner = subprocess_runner,
                 changed: Collection[Path] | None = None) -> str | None:
    """Apply the fleet directory's current state to its running deployment, if any.

    Args:
        changed: the files the command changed (created, updated or deleted); the note
            says auth.yaml is reloaded only when it is among them. ``None``: not known,
            the note says the server reloads it if it changed.

    Returns:
        A one-line note of what was applied, said only of what changed (WireGuard peers
        added or removed, auth.yaml, the server restarted or recreated, simulated robots),
        or ``None`` when no deployment of this fleet runs (nothing to do: the next
        ``fleetctl up`` uses the new files).

    Raises:
        FleetError: the deployment runs but could not be updated (the message says how far
            it got; the fleet directory is already changed, so ``fleetctl up`` retries it).
    """
    options = saved_options(fleet_dir)
    if options is None:
        return None
    if (unasked := docker_unreachable(runner)) is not None:
        # The change is made; only whether a deployment runs is unknown. It was silent
        # (docker ps failing read as "not running") or, without a docker command, an
        # exit 5 after the change, as if the command had failed.
        return (f"warning: a deployment of this fleet was started here, but Docker cannot "
                f"be asked whether it runs ({unasked}): if it does, run `fleetctl up` with "
                "its options once Docker answers (auth.yaml reaches a running server by "
                "itself)")
    server = composerun.container_id(fleet_dir, options.project, "server", runner)
    if server is None:
        return None
    done = []
    if _has_wireguard(server, runner):
        # The peers before and after say what syncconf changed: users are token
        # identities, and a note "WireGuard peers synced" after add-user or remove-user
        # claimed a change to the tunnel that never happened.
        before = _peers(server, runner)
        sync = f"wg syncconf {WG_INTERFACE} <(wg-quick strip {SERVER_WG_CONF})"
        check(runner(["docker", "exec", server, "bash", "-c", sync], None, True),
              "wg syncconf in the server container")
        if (peers := _peer_change(before, _peers(server, runner))) is not None:
            done.append(peers)
    auth = _auth_note(changed)
    plan = plan_for(fleet_dir, options)
    deployed = _deployed_compose(plan)
    if _without_robots(deployed) != _without_robots(render(plan)):
        try:
            composerun.up(fleet_dir, options, progress=progress, runner=runner)
        except FleetError as exc:
            raise FleetError(f"{'; '.join(done) or 'nothing applied'}; then, recreating the "
                             f"server with its new definition: {exc}") from None
        done += ["server recreated with its new compose definition", *auth]
        return "running fleet: " + "; ".join(done)
    loaded_at_start = [what for what, yes in (("TLS certificate", _certificate_changed(plan)),
                                              ("server.yaml", _server_config_changed(plan)))
                       if yes]
    if loaded_at_start:
        # The server loads its certificate and server.yaml at start: a new one (set-endpoint
        # regenerates the self-signed certificate for the new name; render a server.yaml
        # with fleet.yaml's new recording section) needs a restart; robots reconnect on
        # their own.
        write_files(plan)
        # With replicas the server container is the tunnel and network they live in:
        # restart the replicas, which load the certificate, not it.
        for name in replica_names(options.replicas) if options.replicas > 1 else ["server"]:
            cid = composerun.container_id(fleet_dir, options.project, name, runner)
            if cid is not None:
                check(runner(["docker", "restart", cid], None, True), f"restart of {name}")
        done.append(f"server restarted with the new {' and '.join(loaded_at_start)}")
    if options.sim:
        robots_changed = _robots(deployed) != _robots(render(plan))
        try:
            composerun.up(fleet_dir, options, progress=progress, runner=runner,
                          robots_only=True)
        except FleetError as exc:
            raise FleetError(f"{'; '.join(done) or 'nothing applied'}; then: {exc}") from None
        if robots_changed:
            done.append("simulated robots updated")
    done += auth
    return "running fleet: " + ("; ".join(done) or "nothing to apply")


def _auth_note(changed: Collection[Path] | None) -> list[str]:
    """The note on auth.yaml: the server watches the file (mounted live) and reloads it
    itself, so only a change of it is worth a word."""
    if changed is None:
        return ["auth.yaml, if changed, is reloaded by the server itself"]
    if any(Path(p).parts[-2:] == ("server", "auth.yaml") for p in changed):
        return ["auth.yaml changed: the server reloads it by itself (within a second)"]
    return []


def _peers(server: str, runner: Runner) -> frozenset[str] | None:
    """The public keys of the tunnel's peers; ``None``: ``wg`` did not answer."""
    res = runner(["docker", "exec", server, "wg", "show", WG_INTERFACE, "peers"], None, True)
    return frozenset(res.stdout.split()) if res.returncode == 0 else None


def _peer_change(before: frozenset[str] | None, after: frozenset[str] | None) -> str | None:
    """What ``wg syncconf`` changed, or ``None`` when nothing did."""
    if before is None or after is None:
        return "WireGuard peers reloaded (which changed is unknown: `wg show` failed)"
    added, removed = len(after - before), len(before - after)
    if not added and not removed:
        return None
    return f"WireGuard peers: {added} added, {removed} removed"


def _deployed_compose(plan: ComposePlan) -> object:
    """The compose file the deployment runs from, ``None`` when it cannot be read (then
    the server's definition counts as changed)."""
    try:
        return yaml.safe_load(read_small(plan.compose_file, MAX_CONFIG_BYTES))
    except (OSError, yaml.YAMLError):
        return None


def _robots(document: object) -> object:
    if not isinstance(document, dict) or not isinstance(document.get("services"), dict):
        return None
    return {name: svc for name, svc in document["services"].items()
            if str(name).startswith(ROBOT_SERVICE_PREFIX)}


def _without_robots(document: object) -> object:
    if not isinstance(document, dict) or not isinstance(document.get("services"), dict):
        return document
    services = {name: svc for name, svc in document["services"].items()
                if not str(name).startswith(ROBOT_SERVICE_PREFIX)}
    return {**document, "services": services}


def _certificate_changed(plan: ComposePlan) -> bool:
    deployed = plan.compose_dir / "server" / "tls-cert.pem"
    try:
        return (read_small(deployed, MAX_PEM_BYTES)
                != read_small(plan.tls_cert, MAX_PEM_BYTES))
    except OSError:
        return True


def _server_config_changed(plan: ComposePlan) -> bool:
    """Whether the server.yaml the deployment runs with differs from the fleet's now (the
    replicas' configs are made from the same one, with ports the deployment fixes)."""
    deployed = plan.compose_dir / "server" / "server.yaml"
    try:
        return read_small(deployed, MAX_CONFIG_BYTES) != server_config_text(plan).encode()
    except OSError:
        return True


def _has_wireguard(server: str, runner: Runner) -> bool:
    res = runner(["docker", "exec", server, "wg", "show", WG_INTERFACE], None, True)
    return res.returncode == 0
