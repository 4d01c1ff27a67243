"""Fleet life-cycle commands: init, set-endpoint, add-robot, remove-robot, add-user,
set-user, remove-user, list, render, export.

Each command calls one function of :mod:`fleetctl.deploy.operations` (or
:mod:`fleetctl.deploy.export`) and prints its result with :mod:`fleetctl.cli.output`.
The fleet directory comes from ``--fleet DIR``, else ``$FLEET_DIR``, else the current
directory. After a command that changed the fleet (not a dry run), a running deployment
of it is brought up to date (:func:`fleetctl.deploy.live.sync_running`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from fleetctl.cli.output import (
    PORT,
    AsciiInt,
    OutputFormat,
    changes_text,
    emit,
    fleet_option,
    output_option,
    progress_line,
    table,
    warn,
)
from fleetctl.deploy import operations as ops
from fleetctl.deploy.export import export_robot
from fleetctl.deploy.files import ChangeKind
from fleetctl.deploy.fleet import (
    DEFAULT_HTTPS_PORT,
    DEFAULT_MTU_BYTES,
    DEFAULT_SERVER_PORT,
    DEFAULT_SUBNET,
    MAX_MTU_BYTES,
    MIN_MTU_BYTES,
    Fleet,
)
from fleetctl.deploy.userscope import scope_text
from fleetctl.errors import ConfigError, ExitCode, FleetError

_DRY_RUN_HELP = "Show what would be written, write nothing."


def _dry_run_option() -> Any:
    return typer.Option(False, "--dry-run", help=_DRY_RUN_HELP)


def _robots_option(help_text: str) -> Any:
    return typer.Option([], "--robots", metavar="NAME[,NAME...]", help=help_text)


def _robot_names(values: list[str]) -> tuple[str, ...] | None:
    """The names of ``--robots`` (repeatable, each comma-separated) in the order given;
    ``None`` when the option is absent.

    Raises:
        FleetError: (usage) an empty name, as in ``--robots ""`` or ``a,,b``.
    """
    if not values:
        return None
    names = tuple(n.strip() for v in values for n in v.split(","))
    if "" in names:
        given = " ".join(f"--robots {v!r}" for v in values)
        raise FleetError(f"--robots: an empty robot name in {given}",
                         exit_code=ExitCode.USAGE)
    return names


def _header(outcome: ops.Outcome, done: str, would: str) -> str:
    """The first line (*done*, or for a dry run ``dry run: `` and *would*: what would be
    done, never said as done) and the list of changes."""
    first = f"dry run: {would}" if outcome.dry_run else done
    return f"{first}\n" + changes_text(outcome.changes, outcome.fleet_dir, outcome.dry_run)


def _endpoint_text(f: Fleet) -> str:
    return f.endpoint or "endpoint not set (fleetctl set-endpoint HOST:PORT)"


def _finish(outcome: ops.Outcome, output: OutputFormat) -> None:
    """Print the outcome's warnings, then bring a running deployment up to date."""
    for line in outcome.warnings:
        warn(line)
    if outcome.dry_run:
        return
    # Imported here: only change commands need it, and it may pull in Docker tooling.
    from fleetctl.deploy.live import sync_running

    changed = [c.path for c in outcome.changes if c.kind is not ChangeKind.UNCHANGED]
    note = sync_running(outcome.fleet_dir, progress_line, changed=changed)
    if note is not None:
        # JSON on stdout stays one parseable document; the note goes to stderr then.
        typer.echo(note, err=output is OutputFormat.JSON)


def _require_one_directory(ctx: typer.Context, directory: Path | None, fleet: Path) -> None:
    """Refuse ``init DIR --fleet OTHER``: the fleet went into DIR and OTHER was dropped
    without a word. ``$FLEET_DIR`` beside the argument is fine (the argument names the new
    fleet), and so is the same directory twice.

    Raises:
        FleetError: both given on the command line, naming different directories (exit 2).
    """
    source = ctx.get_parameter_source("fleet")
    if (directory is None or source is None or source.name != "COMMANDLINE"
            or directory.resolve() == fleet.resolve()):
        return
    raise FleetError(f"init: the directory {str(directory)!r} and --fleet {str(fleet)!r} "
                     "differ: give the new fleet's directory once", exit_code=ExitCode.USAGE)


def init(
    ctx: typer.Context,
    directory: Path | None = typer.Argument(
        None, help="Directory to create the fleet in (default: --fleet / $FLEET_DIR / .)."),
    endpoint: str | None = typer.Option(
        None, "--endpoint", help="HOST:PORT robots reach WireGuard on (default: none yet; "
        "set it later with `fleetctl set-endpoint`)."),
    subnet: str = typer.Option(DEFAULT_SUBNET, "--subnet", help="VPN subnet (CIDR)."),
    server_ip: str | None = typer.Option(
        None, "--server-ip", help="Server's VPN address (default: first host of the subnet)."),
    server_port: int = typer.Option(DEFAULT_SERVER_PORT, "--server-port", parser=PORT,
                                    help="TCP port of the fleet server's WebSocket."),
    wireguard_port: int | None = typer.Option(
        None, "--wireguard-port", parser=PORT,
        help="UDP port WireGuard listens on (default: the endpoint's port, else 51820)."),
    https_port: int = typer.Option(DEFAULT_HTTPS_PORT, "--https-port", parser=PORT,
                                   help="TCP port of the HTTPS listener (web page, wss://)."),
    name: str | None = typer.Option(
        None, "--name", help="Fleet name: up to 63 ASCII letters, digits, '.', '_', '-' "
        "(default: the directory's name, other characters made '-')."),
    force: bool = typer.Option(False, "--force",
                               help="Replace an existing fleet, its keys and generated files."),
    fleet: Path = fleet_option(),
    dry_run: bool = _dry_run_option(),
    output: OutputFormat = output_option(),
) -> None:
    """Create a fleet: fleet.yaml, server keys and configs, auth map, HTTPS certificate.

    Writes fleet.yaml, the server's WireGuard key and config, server.yaml,
    auth.yaml and a self-signed HTTPS certificate for the web page."""
    _require_one_directory(ctx, directory, fleet)
    result = ops.create_fleet(
        directory or fleet, endpoint=endpoint, name=name, subnet=subnet, server_ip=server_ip,
        server_port=server_port, wireguard_port=wireguard_port, https_port=https_port,
        force=force, dry_run=dry_run)
    f = result.fleet

    def text() -> str:
        what = (f"fleet {f.name!r}: subnet {f.subnet}, server {f.server_ip}, WireGuard "
                f"{_endpoint_text(f)}")
        out = _header(result.outcome, what, f"would create {what}")
        if result.server_public_key is None:  # a dry run: the real run makes another key
            return (out + "\nserver WireGuard key pair: would be made by the real run (its "
                    "public key is printed then, and by `fleetctl list`)"
                    + f"\nHTTPS port {f.https_port}: a self-signed certificate would be made "
                    "(server/tls/cert.pem; set tls in fleet.yaml to use your own)")
        return (out + f"\nserver public key: {result.server_public_key}"
                + f"\nHTTPS port {f.https_port}: self-signed certificate server/tls/cert.pem "
                "(set tls in fleet.yaml to use your own)")

    emit(result, output, text)


def add_robot(
    name: str = typer.Argument(..., help="Robot name (a ROS namespace segment)."),
    ip: str | None = typer.Option(None, "--ip", help="VPN address (default: next free one)."),
    # The range fleet.yaml allows: out of it is a usage error (exit 2) like a port out of
    # range, whether above 65535 or below 576 (once exit 2 and exit 3 with two messages).
    mtu: int = typer.Option(DEFAULT_MTU_BYTES, "--mtu",
                            parser=AsciiInt(MIN_MTU_BYTES, MAX_MTU_BYTES),
                            help=f"WireGuard MTU in bytes, {MIN_MTU_BYTES}..{MAX_MTU_BYTES} "
                            "(1280 suits LTE)."),
    fleet: Path = fleet_option(),
    dry_run: bool = _dry_run_option(),
    output: OutputFormat = output_option(),
) -> None:
    """Add a robot: keys, WireGuard and client configs, server peer, auth rules."""
    with ops.fleet_lock(fleet, dry_run=dry_run):
        result = ops.add_robot(fleet, name, ip=ip, mtu_bytes=mtu, dry_run=dry_run)

    def text() -> str:
        what = f"robot {name!r} at {result.robot.ip}"
        out = _header(result.outcome, what, f"would add {what}")
        if dry_run:  # its key pair was made for the preview only and is not kept
            return out
        return (out + f"\npublic key: {result.public_key}"
                + f"\nnext: fleetctl export {name}   (the bundle to copy to the robot)")

    emit(result, output, text)
    _finish(result.outcome, output)


def remove_robot(
    name: str = typer.Argument(..., help="Robot to remove."),
    fleet: Path = fleet_option(),
    dry_run: bool = _dry_run_option(),
    force: bool = typer.Option(
        False, "--force",
        help="Also delete files under robots/NAME/ that fleetctl did not write or that "
             "were edited by hand (without it, such files stop the removal)."),
    output: OutputFormat = output_option(),
) -> None:
    """Remove a robot, its keys and files, its server peer and its auth rules."""
    with ops.fleet_lock(fleet, dry_run=dry_run):
        result = ops.remove_robot(fleet, name, dry_run=dry_run, force=force)
    emit(result, output, lambda: _header(result.outcome, f"removed robot {name!r}",
                                         f"would remove robot {name!r}"))
    _finish(result.outcome, output)


def add_user(
    email: str = typer.Argument(..., help="The user's email address."),
    role: str = typer.Option(..., "--role", help="viewer, operator or admin."),
    robots: list[str] = _robots_option(
        "Only these robots: what the user sees and, as operator, commands (comma-"
        "separated or repeated; default: every robot; not for an admin)."),
    fleet: Path = fleet_option(),
    dry_run: bool = _dry_run_option(),
    output: OutputFormat = output_option(),
) -> None:
    """Add a user; prints their token once (only its SHA-256 is stored)."""
    names = _robot_names(robots)
    with ops.fleet_lock(fleet, dry_run=dry_run):
        result = ops.add_user(fleet, email, role, robots=names, dry_run=dry_run)
    shown = {"user": result.user, "outcome": result.outcome,
             "token": result.token.reveal() if result.token else None}

    def text() -> str:
        scope = "" if names is None else f", robots {scope_text(names)}"
        what = f"user {email!r} ({result.user.role.value}{scope})"
        out = _header(result.outcome, what, f"would add {what}")
        if result.token is not None:
            out += f"\ntoken (shown once, store it now): {result.token.reveal()}"
        return out

    emit(shown, output, text)
    _finish(result.outcome, output)


def set_user(
    email: str = typer.Argument(..., help="The user to change."),
    robots: list[str] = _robots_option(
        "Scope the user to these robots only (comma-separated or repeated)."),
    all_robots: bool = typer.Option(False, "--all-robots",
                                    help="Let the user use every robot again."),
    fleet: Path = fleet_option(),
    dry_run: bool = _dry_run_option(),
    output: OutputFormat = output_option(),
) -> None:
    """Change the robots a user may use; their token stays the same.

    Give --robots or --all-robots. auth.yaml is re-rendered, and a running server
    applies it to the user's open connections."""
    names = _robot_names(robots)
    if (names is None) == (not all_robots):
        raise FleetError("set-user: give --robots NAME[,NAME...] or --all-robots (one of "
                         "them)", exit_code=ExitCode.USAGE)
    with ops.fleet_lock(fleet, dry_run=dry_run):
        result = ops.set_user_robots(fleet, email, names, dry_run=dry_run)

    def text() -> str:
        what = (f"user {email!r} ({result.user.role.value}) robots: "
                f"{scope_text(result.user.robots)} (was: {scope_text(result.previous_robots)})")
        return _header(result.outcome, f"set {what}", f"would set {what}")

    emit(result, output, text)
    _finish(result.outcome, output)


def remove_user(
    email: str = typer.Argument(..., help="User to remove."),
    fleet: Path = fleet_option(),
    dry_run: bool = _dry_run_option(),
    output: OutputFormat = output_option(),
) -> None:
    """Remove a user; their token stops working once the server reloads auth.yaml."""
    with ops.fleet_lock(fleet, dry_run=dry_run):
        result = ops.remove_user(fleet, email, dry_run=dry_run)
    emit(result, output, lambda: _header(result.outcome, f"removed user {email!r}",
                                         f"would remove user {email!r}"))
    _finish(result.outcome, output)


def list_fleet(
    fleet: Path = fleet_option(),
    output: OutputFormat = output_option(),
) -> None:
    """List the fleet's robots and users.

    A key or TLS file that cannot be read does not hide the rest:
    all else is listed, then one error line names the file (exit 3).
    """
    info = ops.describe_fleet(fleet)
    f = info.fleet

    def robot_key(name: str) -> str:
        if name in info.unreadable_robot_keys:
            return "(key files unreadable: see the error)"
        return info.robot_public_keys.get(name, "(no keys yet)")

    def text() -> str:
        robots = table(["ROBOT", "IP", "MTU", "COMMAND TOPICS", "PUBLIC KEY"], [
            (r.name, r.ip, r.mtu_bytes, ",".join(c.topic for c in r.command_topics) or "-",
             robot_key(r.name)) for r in f.robots])
        users = table(["USER", "ROLE", "ROBOTS"], [
            (u.email, u.role.value, "all" if u.robots is None else ",".join(u.robots))
            for u in f.users])
        server_key = info.server_public_key or "(key file unreadable: see the error)"
        return (f"fleet {f.name!r}: subnet {f.subnet}, server {f.server_ip}:{f.server_port}, "
                f"WireGuard {_endpoint_text(f)}, HTTPS port {f.https_port}\n"
                f"server public key: {server_key}\n\n"
                f"{robots if f.robots else '(no robots)'}\n\n{users if f.users else '(no users)'}")

    emit(info, output, text)
    if len(info.problems) == 1:
        raise ConfigError(info.problems[0])
    if info.problems:  # still one line: numbered, as each may hold a ';' of its own
        raise ConfigError(f"{len(info.problems)} problems: " + " ".join(
            f"[{i}] {problem}" for i, problem in enumerate(info.problems, 1)))


def render(
    force: bool = typer.Option(False, "--force",
                               help="Overwrite generated files that were edited by hand."),
    fleet: Path = fleet_option(),
    dry_run: bool = _dry_run_option(),
    output: OutputFormat = output_option(),
) -> None:
    """Regenerate every config from fleet.yaml and the keys (unchanged files stay untouched)."""
    with ops.fleet_lock(fleet, dry_run=dry_run):
        outcome = ops.render_fleet(fleet, dry_run=dry_run, force=force)
    emit(outcome, output, lambda: _header(outcome, f"rendered {outcome.fleet_dir}",
                                          f"would render {outcome.fleet_dir}"))
    _finish(outcome, output)


def set_endpoint(
    endpoint: str = typer.Argument(..., help="HOST:PORT robots reach the server's WireGuard on."),
    fleet: Path = fleet_option(),
    dry_run: bool = _dry_run_option(),
    output: OutputFormat = output_option(),
) -> None:
    """Set where robots reach the server's WireGuard (HOST:PORT), then re-render."""
    with ops.fleet_lock(fleet, dry_run=dry_run):
        result = ops.set_endpoint(fleet, endpoint, dry_run=dry_run)

    def text() -> str:
        what = f"endpoint {result.endpoint} (was {result.previous or 'not set'})"
        out = _header(result.outcome, what, f"would set {what}")
        if result.certificate_regenerated:
            out += ("\nself-signed HTTPS certificate would be made again for the new host"
                    if dry_run else "\nself-signed HTTPS certificate made again for the new host")
        return out

    emit(result, output, text)
    _finish(result.outcome, output)


def export(
    name: str = typer.Argument(..., help="Robot to export."),
    out: Path | None = typer.Option(
        None, "--out", help="Bundle directory (made 0700 if missing), or a path ending in "
        ".tar.gz or .tgz (default: ./NAME-bundle)."),
    fleet: Path = fleet_option(),
    dry_run: bool = _dry_run_option(),
    output: OutputFormat = output_option(),
) -> None:
    """Write robot NAME's bundle: its WireGuard config, client config and how to start them."""
    result = export_robot(fleet, name, out, dry_run=dry_run)
    what = f"bundle of {name!r}: {result.path}"
    emit(result, output, lambda: _header(result.outcome, what, f"would write the {what}"))


def register(app: typer.Typer) -> None:
    """Add this group's commands to *app*."""
    app.command("init")(init)
    app.command("set-endpoint")(set_endpoint)
    app.command("add-robot")(add_robot)
    app.command("remove-robot")(remove_robot)
    app.command("add-user")(add_user)
    app.command("set-user")(set_user)
    app.command("remove-user")(remove_user)
    app.command("list")(list_fleet)
    app.command("render")(render)
    app.command("export")(export)
