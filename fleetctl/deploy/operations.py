"""The fleet life cycle as library functions: each validates everything first, then
applies one :class:`~fleetctl.deploy.files.Plan` (or only previews it with ``dry_run``).

These return results and print nothing; ``fleetctl.cli.fleet`` renders them, and other
code (``fleetctl demo``, tests) calls them directly. Bad input raises a
:class:`~fleetctl.errors.FleetError` and leaves the fleet directory untouched.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shlex
import stat
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from ipaddress import IPv4Address
from pathlib import Path

from fleetctl.client.mediaconfig import TfSpec
from fleetctl.deploy import keystore, tls
from fleetctl.deploy.files import (
    PUBLIC_FILE_MODE,
    SECRET_DIR_MODE,
    Change,
    FileWrite,
    Plan,
    WriteFailed,
    is_untouched,
)
from fleetctl.deploy.fleet import (
    DEFAULT_COMMAND_TOPICS,
    DEFAULT_HTTPS_PORT,
    DEFAULT_MTU_BYTES,
    DEFAULT_SERVER_PORT,
    DEFAULT_SUBNET,
    DEFAULT_WIREGUARD_PORT,
    Fleet,
    FleetInvalid,
    Robot,
    Role,
    User,
    check_fleet_name,
    check_robot_name,
    default_fleet_name,
    dump_fleet,
    fleet_file,
    load_fleet,
    next_free_ip,
    not_a_directory,
    parse_endpoint,
    parse_ip,
    parse_subnet,
    validate,
)
from fleetctl.deploy.keys import (
    KeySource,
    SystemKeySource,
    new_private_key,
    new_token,
    public_key,
    token_sha256,
)
from fleetctl.deploy.keystore import RobotKeys
from fleetctl.deploy.render import (
    ROBOT_FILES,
    ROBOT_WIREGUARD_FILE,
    FleetKeys,
    fleet_artifacts,
    plan_artifacts,
)
from fleetctl.deploy.replaynames import check_not_replay_name
from fleetctl.deploy.secrets import Secret
from fleetctl.deploy.userscope import check_scope, without_robot
from fleetctl.deploy.yamlnodes import FieldPath, format_path
from fleetctl.errors import ConfigError, ConflictError, ExitCode, FleetError
from fleetctl.smallfile import MAX_CONFIG_BYTES, read_small

_SYSTEM_KEYS = SystemKeySource()
# The certificate is never byte-reproducible (its signature is randomized, its dates are
# today's), so its key always comes from the OS: injected sources stay for WireGuard keys
# and tokens, whose sequence golden files pin.
_TLS_KEYS = SystemKeySource()
# What `init --force` replaces: only what fleetctl itself generates.
_GENERATED = ("server", "robots", keystore.KEYS_DIR)


@dataclass(frozen=True)
class Outcome:
    """What an operation did (or, with ``dry_run``, would do) to the fleet directory.

    Attributes:
        fleet_dir: the directory.
        changes: per file, in the order applied.
        dry_run: nothing was written.
        warnings: one line each: something the result still lacks, and the command that
            fixes it (e.g. no endpoint yet).
    """

    fleet_dir: Path
    changes: tuple[Change, ...]
    dry_run: bool
    warnings: tuple[str, ...] = ()


@dataclass(frozen=True)
class EndpointResult:
    """Result of :func:`set_endpoint`."""

    endpoint: str
    previous: str | None
    certificate_regenerated: bool
    outcome: Outcome


@dataclass(frozen=True)
class InitResult:
    """Result of :func:`create_fleet`.

    Attributes:
        server_public_key: ``None`` for a dry run: the key pair made for the preview is
            thrown away and the real run makes another, so its public key would be false.
    """

    fleet: Fleet
    server_public_key: str | None
    outcome: Outcome


@dataclass(frozen=True)
class RobotResult:
    """Result of :func:`add_robot` / :func:`remove_robot`."""

    robot: Robot
    public_key: str | None  # None for a removed robot
    outcome: Outcome


@dataclass(frozen=True)
class UserResult:
    """Result of :func:`add_user` / :func:`remove_user`.

    ``token`` is the new user's token, shown once: only its hash is stored. It is ``None``
    for a removal and for a dry run (nothing is stored, so a token would be useless).
    """

    user: User
    token: Secret | None
    outcome: Outcome


@dataclass(frozen=True)
class ScopeResult:
    """Result of :func:`set_user_robots`: the user as they are now, and their robots
    before (``None``: every robot)."""

    user: User
    previous_robots: tuple[str, ...] | None
    outcome: Outcome


@dataclass(frozen=True)
class FleetInfo:
    """Result of :func:`describe_fleet`: the fleet and its public keys (never private ones).

    Attributes:
        fleet_dir: The fleet directory.
        fleet: Its fleet.yaml.
        server_public_key: ``None``: its key file could not be read (see *problems*).
        robot_public_keys: By robot name; a robot that is not here has no keys yet, or
            ones that could not be read (its name is in *unreadable_robot_keys*).
        unreadable_robot_keys: Robots whose key files are missing or bad.
        problems: One line per file that could not be read (naming it and what to do),
            in the order found; empty when everything was read.
    """

    fleet_dir: Path
    fleet: Fleet
    server_public_key: str | None
    robot_public_keys: dict[str, str]
    unreadable_robot_keys: tuple[str, ...] = ()
    problems: tuple[str, ...] = ()


@dataclass(frozen=True)
class ExportResult:
    """Result of :func:`export_robot`: the bundle written at ``path``."""

    robot: Robot
    path: Path
    outcome: Outcome


# --- helpers ---------------------------------------------------------------------------


def _describe(fleet: Fleet, path: FieldPath) -> str:
    if len(path) >= 2 and path[0] == "robots" and isinstance(path[1], int):
        rest = format_path(path[2:]) if path[2:] else "robot"
        return f"robot {fleet.robots[path[1]].name!r}: {rest}"
    if len(path) >= 2 and path[0] == "users" and isinstance(path[1], int):
        rest = format_path(path[2:]) if path[2:] else "user"
        return f"user {fleet.users[path[1]].email!r}: {rest}"
    return format_path(path)


def _checked(fleet: Fleet) -> Fleet:
    """Validate a fleet built from command input; raise the CLI-facing error."""
    try:
        validate(fleet)
    except FleetInvalid as exc:
        raise _error(fleet, exc) from None
    return fleet


# The command-line option each top-level field of fleet.yaml comes from in `init`.
_INIT_OPTIONS = {"name": "--name", "endpoint": "--endpoint", "subnet": "--subnet",
                 "server_ip": "--server-ip", "server_port": "--server-port",
                 "wireguard_port": "--wireguard-port", "https_port": "--https-port"}


def _option_error(exc: FleetInvalid) -> FleetError:
    """The error of a bad `init` argument, naming the field and its option."""
    field_name = format_path(exc.path)
    option = _INIT_OPTIONS.get(field_name)
    where = f"{field_name} ({option})" if option else field_name
    return (ConflictError if exc.conflict else ConfigError)(f"{where}: {exc}")


def _error(fleet: Fleet, exc: FleetInvalid) -> FleetError:
    message = f"{_describe(fleet, exc.path)}: {exc}"
    return ConflictError(message) if exc.conflict else ConfigError(message)


def _load_keys(fleet_dir: Path, fleet: Fleet, source: KeySource, plan: Plan) -> FleetKeys:
    """Read every key; make (and plan to write) keys for robots that have none yet.

    A robot added to fleet.yaml by hand gets its keys on the next operation; a missing
    server key is an error, because a new one would cut off every robot already deployed.
    So are the missing keys of a robot whose WireGuard config was generated already: that
    config (and the bundle exported from it) holds the keys the robot may be using, and new
    ones would cut it off without a word (a fleet directory restored without ``keys/``).
    """
    for directory in (fleet_dir / keystore.KEYS_DIR, fleet_dir / keystore.KEYS_DIR / "robots"):
        # 0700 again if it was opened up (docs: fleetctl forces the mode of the directories
        # it owns); it was forced only when a key was written into it.
        if directory.is_dir() and not directory.is_symlink():
            plan.directory(directory, SECRET_DIR_MODE)
    robots: dict[str, RobotKeys] = {}
    for robot in fleet.robots:
        keys = existing_robot_keys(fleet_dir, robot.name)
        if keys is None:
            keys = keystore.new_robot_keys(source)
            keystore.plan_robot_keys(plan, fleet_dir, robot.name, keys)
        robots[robot.name] = keys
    return FleetKeys(keystore.load_server_key(fleet_dir), robots)


def existing_robot_keys(fleet_dir: Path, name: str) -> RobotKeys | None:
    """Robot *name*'s keys; ``None`` when it has none yet (none were ever made for it).

    Raises:
        ConfigError: a key file is bad, one of the pair is missing, or both are while its
            ``wg0.conf`` made from them is there.
    """
    key_path, psk_path = keystore.robot_key_paths(fleet_dir, name)
    generated = fleet_dir / "robots" / name / ROBOT_WIREGUARD_FILE
    renew = (f"run `fleetctl render` and install a new `fleetctl export {name}` on the "
             "robot")
    for missing, pair in ((key_path, psk_path), (psk_path, key_path)):
        if not os.path.lexists(missing) and os.path.lexists(pair):
            raise ConfigError(f"{missing}: key file not found (its pair {pair.name} is "
                              "there): restore it from a backup, or, to give the robot new "
                              f"keys, delete {pair} and {generated}, {renew}")
    keys = keystore.load_robot_keys(fleet_dir, name)
    if keys is None and os.path.lexists(generated):
        raise ConfigError(
            f"{key_path} and {psk_path.name}: not found, but {generated} was made "
            f"from them and robot {name!r} may be using them: restore them "
            f"from a backup, or, to give the robot new keys, delete {generated}, {renew}")
    return keys


def _plan_fleet(plan: Plan, fleet_dir: Path, fleet: Fleet, keys: FleetKeys, *,
                write_fleet: bool = True, force: bool = False) -> Plan:
    """Plan fleet.yaml (unless *write_fleet* is false) and every artifact.

    Raises:
        ConfigError: (unless *force*) a generated file was edited by hand; fleet.yaml is
            a symbolic link and would change.
    """
    if write_fleet:
        path, text = fleet_file(fleet_dir), dump_fleet(fleet)
        if path.is_symlink() and read_small(path, MAX_CONFIG_BYTES) != text.encode():
            # Every write replaces the file whole (atomically), which would put a copy in
            # place of the link and leave the operator's own file (in a repository, say)
            # behind without a word.
            raise ConfigError(
                f"{path} is a symbolic link (to {os.readlink(path)}): fleetctl replaces "
                "fleet.yaml whole and would replace the link, not the file it points to; "
                "point FLEET_DIR at a directory where fleet.yaml is the file itself")
        plan.writes.append(FileWrite(path, text.encode(), _fleet_file_mode(path)))
    plan_artifacts(plan, fleet_dir, fleet_artifacts(fleet, keys, fleet_dir), force=force)
    return plan


def _fleet_file_mode(path: Path) -> int:
    """fleet.yaml's mode: 0644 when new; an existing one keeps the mode its owner gave it
    (0600, 0640: a command that writes it back made it 0644, readable by all), less any
    write permission for group and others (anyone could add a robot) and exec bits."""
    try:
        mode = stat.S_IMODE(path.lstat().st_mode)
    except OSError:
        return PUBLIC_FILE_MODE
    return mode & 0o644


def _plan_tls(plan: Plan, fleet_dir: Path, fleet: Fleet, *, refresh: bool = False,
              renew: bool = False) -> bool:
    """Make the self-signed HTTPS certificate if the fleet uses one and it is missing.

    Args:
        plan: where the writes go.
        fleet_dir: the fleet directory.
        fleet: the fleet (with ``tls`` set, the operator's files are used: nothing to do).
        refresh: also replace an existing generated certificate whose names are not the
            ones the fleet needs now (the endpoint's host changed).
        renew: also replace one that ends within :data:`tls.RENEW_BEFORE` (``render``;
            other commands never restart the server for it).

    Returns:
        True when a certificate is (re)generated.
    """
    if fleet.tls is not None:
        return False
    cert_path, key_path = fleet_dir / tls.CERT_RELPATH, fleet_dir / tls.KEY_RELPATH
    host = parse_endpoint(fleet.endpoint)[0] if fleet.endpoint else None
    names = tls.san_names(host)
    missing = not (cert_path.is_file() and key_path.is_file())
    if not missing and not (refresh and tls.cert_names(cert_path) != names) and not (
            renew and tls.expires_soon(cert_path) is not None):
        return False
    tls.plan_self_signed(plan, fleet_dir, tls.self_signed(names, _TLS_KEYS))
    return True


def _endpoint_warning(fleet: Fleet, fleet_dir: Path) -> tuple[str, ...]:
    if fleet.endpoint is not None or not fleet.robots:
        return ()
    return (f"{fleet_file(fleet_dir)} has no endpoint, so the robots' wg0.conf have no "
            "Endpoint and cannot reach the server: run `fleetctl set-endpoint HOST:PORT`",)


def finish_plan(plan: Plan, fleet_dir: Path, dry_run: bool,
                warnings: tuple[str, ...] = ()) -> Outcome:
    """Apply *plan* (or only preview it when *dry_run*) and return the outcome.

    Raises:
        ConfigError: a directory below *fleet_dir* the plan writes in is a symbolic link.
        WriteFailed: a file could not be written (nothing was changed).
    """
    if plan.root is None:
        plan.root = fleet_dir
    changes = plan.preview() if dry_run else plan.apply()
    return Outcome(fleet_dir, tuple(changes), dry_run, warnings)


LOCK_FILE = ".fleetctl.lock"


@contextlib.contextmanager
def fleet_lock(fleet_dir: Path, *, dry_run: bool = False) -> Iterator[None]:
    """Hold an exclusive lock on *fleet_dir* (``flock`` on ``FLEET/.fleetctl.lock``) so two
    commands that change the fleet at once run one after the other: each reads fleet.yaml,
    changes it and writes it back, and the later write would drop the earlier change.

    A directory that is not a fleet (missing, or without ``fleet.yaml``) is not locked and
    the lock file is not made there: loading the fleet then reports it, and a failing
    command leaves nothing behind.

    With *dry_run* the lock is shared and the lock file is never created. A dry run writes
    nothing, so it cannot lose another command's change and needs no exclusive lock; making
    the lock file would be a change of its own (and fails in a fleet directory the caller
    may only read, where a preview should still work). A shared lock on an existing lock
    file keeps the preview from reading a fleet halfway through another command's change;
    when there is no lock file yet (no command has changed this fleet) or it cannot be
    opened, the dry run goes on unlocked: at worst it previews a fleet that another
    command is changing at that moment, and it still writes nothing.

    Raises:
        WriteFailed: (exit code 5) the lock file cannot be created or opened, e.g. a fleet
            directory the caller may not write; nothing was changed.
    """
    if not fleet_dir.is_dir() or not os.path.lexists(fleet_file(fleet_dir)):
        yield
        return
    path = fleet_dir / LOCK_FILE
    try:
        if dry_run:
            fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        else:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        if dry_run:
            yield
            return
        raise WriteFailed(f"{path}: cannot write: {exc.strerror or exc}; nothing was "
                          "changed (the lock file of commands that change the fleet; "
                          "--dry-run does not need it)") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH if dry_run else fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


# --- operations ------------------------------------------------------------------------


def create_fleet(
    fleet_dir: Path,
    *,
    endpoint: str | None = None,
    name: str | None = None,
    subnet: str = DEFAULT_SUBNET,
    server_ip: str | None = None,
    server_port: int = DEFAULT_SERVER_PORT,
    wireguard_port: int | None = None,
    https_port: int = DEFAULT_HTTPS_PORT,
    force: bool = False,
    dry_run: bool = False,
    keys: KeySource = _SYSTEM_KEYS,
) -> InitResult:
    """Create a fleet directory: fleet.yaml, server key, server configs, auth map, and a
    self-signed HTTPS certificate.

    Args:
        fleet_dir: the directory (created if missing).
        endpoint: ``HOST:PORT`` robots reach the server's WireGuard on; ``None``: not
            known yet (set it later with :func:`set_endpoint`).
        name: fleet label; default: the directory's name.
        subnet: VPN subnet in CIDR form.
        server_ip: server's VPN address; default: the subnet's first host.
        server_port: TCP port of the fleet server (plain ws://, inside the tunnel).
        wireguard_port: UDP port WireGuard listens on; default: the endpoint's port, else
            51820.
        https_port: TCP port of the HTTPS listener (web page and wss://).
        force: replace an existing fleet (its fleet.yaml, keys and generated files).
        dry_run: compute and return the changes without writing anything.
        keys: where key material comes from.

    Raises:
        ConflictError: *fleet_dir* already holds a fleet and *force* is false.
        ConfigError: an argument is invalid (the message names it).
    """
    _check_can_be_directory(fleet_dir)
    if fleet_file(fleet_dir).exists() and not force:
        raise ConflictError(f"{fleet_file(fleet_dir)} already exists "
                            "(use --force to replace the fleet and all its keys)")
    try:
        if name is not None:
            check_fleet_name(name)
        net = parse_subnet(subnet)
        endpoint_port = parse_endpoint(endpoint)[1] if endpoint else DEFAULT_WIREGUARD_PORT
        server = (parse_ip(server_ip, ("server_ip",)) if server_ip
                  else next(iter(net.hosts()), net.network_address))
        fleet = Fleet(
            name=name or default_fleet_name(fleet_dir),
            endpoint=endpoint or None, subnet=net, server_ip=server, server_port=server_port,
            wireguard_port=wireguard_port or endpoint_port, https_port=https_port,
        )
        validate(fleet)
    except FleetInvalid as exc:
        raise _option_error(exc) from None
    plan = Plan()
    if force:
        for sub in _GENERATED:
            plan.delete(fleet_dir / sub)
    server_key = new_private_key(keys)
    keystore.plan_server_key(plan, fleet_dir, server_key)
    # A fresh certificate (not _plan_tls: with --force the old one is being deleted).
    host = parse_endpoint(endpoint)[0] if endpoint else None
    tls.plan_self_signed(plan, fleet_dir, tls.self_signed(tls.san_names(host), _TLS_KEYS))
    _plan_fleet(plan, fleet_dir, fleet, FleetKeys(server_key, {}), force=force)
    return InitResult(fleet, None if dry_run else public_key(server_key),
                      finish_plan(plan, fleet_dir, dry_run))


def _check_can_be_directory(fleet_dir: Path) -> None:
    """Raise :class:`ConfigError` when *fleet_dir*, or the nearest of its parents that
    exists, is not a directory (a fleet could never be written there)."""
    for path in (fleet_dir, *fleet_dir.absolute().parents):
        if os.path.lexists(path):
            if not path.is_dir():
                raise ConfigError(f"{fleet_dir}: cannot create a fleet here: {path} exists "
                                  "and is not a directory")
            return


def add_robot(
    fleet_dir: Path,
    name: str,
    *,
    ip: str | None = None,
    mtu_bytes: int = DEFAULT_MTU_BYTES,
    dry_run: bool = False,
    keys: KeySource = _SYSTEM_KEYS,
) -> RobotResult:
    """Add a robot: keys, its WireGuard and client configs, a server peer, auth rules.

    Args:
        fleet_dir: the fleet directory.
        name: a ROS namespace segment, unique in the fleet.
        ip: its VPN address; ``None``: the lowest free address of the subnet (an empty
            string is an error).
        mtu_bytes: MTU of its WireGuard interface.
        dry_run: compute and return the changes without writing anything.
        keys: where key material comes from.

    Raises:
        ConfigError: a bad name, address or MTU, or a missing/malformed fleet directory;
            a problem with *ip* or *mtu_bytes* names the option (``ip (--ip): ...``).
        ConflictError: the name or address is taken, or the subnet is full.
    """
    fleet = load_fleet(fleet_dir)
    # The fields of the new robot that come from an option (--ip only when given).
    options = {"mtu_bytes": "--mtu", **({"ip": "--ip"} if ip is not None else {})}
    try:
        check_robot_name(name)
        # New names only: a fleet.yaml that has one already keeps loading (status knows
        # it is the fleet's; the page, which sees no fleet.yaml, marks it as a replay).
        check_not_replay_name(name)
        # An empty --ip is refused (as an empty endpoint is), not taken as "next free".
        address = parse_ip(ip, ("ip",)) if ip is not None else next_free_ip(fleet)
    except FleetInvalid as exc:
        message = (f"robot {name!r}: ip (--ip): {exc}" if exc.path == ("ip",)
                   else str(exc))
        raise (ConflictError(message) if exc.conflict else ConfigError(message)) from None
    # A new robot sends TF (throttled, tf2_web_republisher's defaults): what the page needs
    # to draw its sensors in one scene. fleet.yaml's `tf:` says so and can be removed.
    robot = Robot(name, address, mtu_bytes=mtu_bytes, command_topics=DEFAULT_COMMAND_TOPICS,
                  tf=TfSpec())
    new = replace(fleet, robots=(*fleet.robots, robot))
    try:
        validate(new)
    except FleetInvalid as exc:
        path = exc.path
        option = (options.get(str(path[2]))
                  if len(path) == 3 and path[:2] == ("robots", len(fleet.robots)) else None)
        if option is None:
            raise _error(new, exc) from None
        message = f"robot {name!r}: {path[2]} ({option}): {exc}"
        raise (ConflictError(message) if exc.conflict else ConfigError(message)) from None
    plan = Plan()
    fleet_keys = _load_keys(fleet_dir, new, keys, plan)
    _plan_tls(plan, fleet_dir, new)
    _plan_fleet(plan, fleet_dir, new, fleet_keys)
    pub = public_key(fleet_keys.robot(name).private_key)
    outcome = finish_plan(plan, fleet_dir, dry_run, _endpoint_warning(new, fleet_dir))
    return RobotResult(robot, pub, outcome)


def remove_robot(fleet_dir: Path, name: str, *, dry_run: bool = False,
                 force: bool = False) -> RobotResult:
    """Remove a robot, its keys, its files, its server peer and its auth rules.

    ``robots/NAME/`` goes as a whole, so anything an operator put or edited there would go
    with it: unless *force*, such files stop the removal before anything changes.

    Users scoped to it (``robots`` in fleet.yaml) lose it from their list, each said in
    the outcome's warnings.

    Raises:
        ConfigError: there is no such robot, or the fleet directory is missing/malformed.
        ConflictError: (unless *force*) ``robots/NAME/`` holds files fleetctl did not
            generate, or generated files edited by hand; or it is the only robot of a
            scoped user (:func:`~fleetctl.deploy.userscope.without_robot`).
    """
    fleet = load_fleet(fleet_dir)
    robot = fleet.robot(name)
    if robot is None:
        raise ConfigError(f"robot {name!r} is not in {fleet_file(fleet_dir)}")
    users, notes = without_robot(fleet, fleet_dir, name, dry_run=dry_run)
    robot_dir = fleet_dir / "robots" / name
    kept = [] if force else _operator_files(robot_dir)
    if kept:
        shown = ", ".join(kept[:5]) + (f" and {len(kept) - 5} more" if len(kept) > 5 else "")
        raise ConflictError(f"{robot_dir} holds files fleetctl did not write or that were "
                            f"edited by hand ({shown}): move them out of it, or run "
                            f"`fleetctl remove-robot {name} --force` to delete them too")
    new = replace(fleet, robots=tuple(r for r in fleet.robots if r.name != name),
                  users=users)
    plan = Plan()
    fleet_keys = _load_keys(fleet_dir, new, _SYSTEM_KEYS, plan)
    plan.delete(fleet_dir / "robots" / name)
    plan.deletes.extend(keystore.robot_key_paths(fleet_dir, name))
    _plan_tls(plan, fleet_dir, new)
    _plan_fleet(plan, fleet_dir, new, fleet_keys)
    return RobotResult(robot, None, finish_plan(plan, fleet_dir, dry_run, notes))


# What fleetctl writes under robots/NAME/, relative to it, and the directories they need.
_ROBOT_FILES = frozenset(ROBOT_FILES)
_ROBOT_DIRS = frozenset({"", *(os.path.dirname(f) for f in ROBOT_FILES)})


def _operator_files(robot_dir: Path) -> list[str]:
    """What under *robot_dir* is not an untouched generated file (relative paths, sorted):
    files and links someone added, and generated files edited since."""
    found: list[str] = []
    for top, dirs, files in os.walk(robot_dir):  # links to directories are not entered
        rel_top = os.path.relpath(top, robot_dir)
        rel_top = "" if rel_top == "." else rel_top
        for d in dirs:
            rel = os.path.join(rel_top, d)
            if rel not in _ROBOT_DIRS or os.path.islink(os.path.join(top, d)):
                found.append(rel)
        for f in files:
            rel = os.path.join(rel_top, f)
            if rel not in _ROBOT_FILES or not _untouched(Path(top) / f):
                found.append(rel)
    return sorted(found)


def _untouched(path: Path) -> bool:
    try:
        return is_untouched(read_small(path, MAX_CONFIG_BYTES, follow_symlinks=False))
    except OSError:
        return False  # a link, a device, unreadable: not fleetctl's to delete unasked


def parse_role(text: str) -> Role:
    """Return the role named *text*.

    Raises:
        FleetError: (usage exit code) naming the valid roles.
    """
    try:
        return Role(text)
    except ValueError:
        valid = ", ".join(r.value for r in Role)
        raise FleetError(f"unknown role {text!r} (expected one of {valid})",
                         exit_code=ExitCode.USAGE) from None


def add_user(
    fleet_dir: Path,
    email: str,
    role: Role | str,
    *,
    robots: Sequence[str] | None = None,
    dry_run: bool = False,
    keys: KeySource = _SYSTEM_KEYS,
) -> UserResult:
    """Add a user with a new token; only the token's SHA-256 is stored.

    Args:
        fleet_dir: the fleet directory.
        email: who.
        role: what they may do.
        robots: the only robots they see and (as operator) command; ``None``: every robot.
        dry_run: compute and return the changes without writing anything.
        keys: where key material comes from.

    Raises:
        FleetError: unknown role, *robots* given to an admin, empty or with a name twice
            (usage); bad email or an unknown robot (config); existing user (conflict).
    """
    role = role if isinstance(role, Role) else parse_role(role)
    fleet = load_fleet(fleet_dir)
    scope = None if robots is None else tuple(robots)
    if scope is not None:
        check_scope(fleet, fleet_dir, role, scope)
    if (known := fleet.user(email)) is not None:
        # The one thing an operator then wants: a new token for someone who lost theirs
        # (with their scope: added again without it, they would see every robot).
        again = ("" if known.robots is None else
                 f" with --robots {shlex.quote(','.join(known.robots))}")
        raise ConflictError(
            f"user {email!r} is already in {fleet_file(fleet_dir)} ({known.role.value}): to "
            f"give them a new token, `fleetctl remove-user {shlex.quote(email)}` (their old "
            f"token stops working) and add them again{again}")
    token = new_token(keys)
    user = User(email, role, token_sha256(token), scope)
    new = _checked(replace(fleet, users=(*fleet.users, user)))
    plan = Plan()
    _plan_tls(plan, fleet_dir, new)
    _plan_fleet(plan, fleet_dir, new, _load_keys(fleet_dir, new, keys, plan))
    outcome = finish_plan(plan, fleet_dir, dry_run)
    return UserResult(user, None if dry_run else token, outcome)


def remove_user(fleet_dir: Path, email: str, *, dry_run: bool = False) -> UserResult:
    """Remove a user (their token stops working when the server reloads auth.yaml).

    Raises:
        ConfigError: there is no such user, or the fleet directory is missing/malformed.
    """
    fleet = load_fleet(fleet_dir)
    user = _existing_user(fleet, fleet_dir, email)
    new = replace(fleet, users=tuple(u for u in fleet.users if u.email != email))
    plan = Plan()
    _plan_tls(plan, fleet_dir, new)
    _plan_fleet(plan, fleet_dir, new, _load_keys(fleet_dir, new, _SYSTEM_KEYS, plan))
    return UserResult(user, None, finish_plan(plan, fleet_dir, dry_run))


def _existing_user(fleet: Fleet, fleet_dir: Path, email: str) -> User:
    """The user *email*; a ConfigError naming the one that differs only in case, if any."""
    user = fleet.user(email)
    if user is None:
        near = next((u.email for u in fleet.users if u.email.casefold() == email.casefold()),
                    None)
        hint = f" (there is {near!r})" if near else ""
        raise ConfigError(f"user {email!r} is not in {fleet_file(fleet_dir)}{hint}")
    return user


def set_user_robots(fleet_dir: Path, email: str, robots: Sequence[str] | None, *,
                    dry_run: bool = False, keys: KeySource = _SYSTEM_KEYS) -> ScopeResult:
    """Scope user *email* to *robots* (``None``: every robot), keeping their token, and
    re-render: the server's auth.yaml changes and a running server reloads it.

    Raises:
        ConfigError: there is no such user, a robot is not in the fleet, or the fleet
            directory is missing/malformed.
        FleetError: (usage) the user is an admin, or *robots* is empty or names a robot
            twice.
    """
    fleet = load_fleet(fleet_dir)
    user = _existing_user(fleet, fleet_dir, email)
    scope = None if robots is None else tuple(robots)
    if scope is not None:
        check_scope(fleet, fleet_dir, user.role, scope)
    changed = replace(user, robots=scope)
    new = _checked(replace(fleet, users=tuple(changed if u is user else u
                                              for u in fleet.users)))
    plan = Plan()
    _plan_tls(plan, fleet_dir, new)
    _plan_fleet(plan, fleet_dir, new, _load_keys(fleet_dir, new, keys, plan))
    return ScopeResult(changed, user.robots, finish_plan(plan, fleet_dir, dry_run))


def render_fleet(fleet_dir: Path, *, dry_run: bool = False, force: bool = False,
                 keys: KeySource = _SYSTEM_KEYS) -> Outcome:
    """Regenerate every artifact from fleet.yaml and the key files.

    fleet.yaml itself is only read, never rewritten (its comments and layout stay).
    Files whose bytes are already right are not touched (their mtime stays), so running it
    twice changes nothing. Robots listed in fleet.yaml without keys get new keys; a missing
    self-signed certificate is made, an existing one kept until its last 30 days (then it
    is made again, and said in a warning).

    Args:
        fleet_dir: the fleet directory.
        dry_run: compute and return the changes without writing anything.
        force: overwrite generated files that were edited by hand.
        keys: where key material comes from.

    Raises:
        ConfigError: the fleet directory, fleet.yaml or a key file is missing or malformed,
            or (without *force*) a generated file was edited by hand.
    """
    fleet = load_fleet(fleet_dir)
    plan = Plan()
    cert_path = fleet_dir / tls.CERT_RELPATH
    ending = tls.expires_soon(cert_path) if fleet.tls is None else None
    _plan_tls(plan, fleet_dir, fleet, renew=True)
    _plan_fleet(plan, fleet_dir, fleet, _load_keys(fleet_dir, fleet, keys, plan),
                write_fleet=False, force=force)
    notes = _endpoint_warning(fleet, fleet_dir)
    if ending is not None:
        # A browser that accepted the old one asks again; `--ca-file` users read the same
        # file, now the new certificate.
        notes += (f"the self-signed HTTPS certificate {cert_path} ends "
                  f"{ending:%Y-%m-%d %H:%M} UTC: made again, valid for a year",)
    return finish_plan(plan, fleet_dir, dry_run, notes)


def set_endpoint(fleet_dir: Path, endpoint: str, *, dry_run: bool = False,
                 keys: KeySource = _SYSTEM_KEYS) -> EndpointResult:
    """Set where robots reach the server's WireGuard, and re-render.

    The self-signed HTTPS certificate (not the operator's own) is made again when the
    endpoint's host is not among its names. ``wireguard_port`` (where the server listens)
    is left alone: behind port forwarding the two may differ.

    Raises:
        ConfigError: *endpoint* is not ``HOST:PORT``, or the fleet directory is bad.
    """
    fleet = load_fleet(fleet_dir)
    try:
        port = parse_endpoint(endpoint)[1]
    except FleetInvalid as exc:
        raise ConfigError(f"{format_path(exc.path)}: {exc}") from None
    new = _checked(replace(fleet, endpoint=endpoint))
    plan = Plan()
    regenerated = _plan_tls(plan, fleet_dir, new, refresh=True)
    _plan_fleet(plan, fleet_dir, new, _load_keys(fleet_dir, new, keys, plan))
    warnings = () if port == new.wireguard_port else (
        f"the endpoint's port {port} is not wireguard_port {new.wireguard_port} (where the "
        f"server's WireGuard listens): right only if UDP {port} is forwarded to "
        f"{new.wireguard_port}; otherwise set wireguard_port: {port} in "
        f"{fleet_file(fleet_dir)} and run `fleetctl render`",)
    outcome = finish_plan(plan, fleet_dir, dry_run, warnings)
    return EndpointResult(endpoint, fleet.endpoint, regenerated, outcome)


def set_relay_replicas(fleet_dir: Path, count: int, *, dry_run: bool = False,
                       keys: KeySource = _SYSTEM_KEYS) -> Outcome:
    """Record that the server host runs *count* relay replicas (``fleet.yaml``
    ``relay_replicas``), and re-render: every robot's ``client.yaml`` then lists every
    replica, so that the bundle exported from it fails over between them. ``up
    --replicas N`` calls this once the deployment is up.

    Raises:
        ConfigError: *count* out of range, replica ports that do not fit, or a bad
            fleet directory.
    """
    fleet = load_fleet(fleet_dir)
    new = _checked(replace(fleet, relay_replicas=count))
    plan = Plan()
    _plan_fleet(plan, fleet_dir, new, _load_keys(fleet_dir, new, keys, plan))
    return finish_plan(plan, fleet_dir, dry_run)


def describe_fleet(fleet_dir: Path) -> FleetInfo:
    """Return the fleet with its public keys (robots without keys yet have none listed).

    Everything fleet.yaml says is returned even when a file beside it cannot be read (a
    key file, the operator's TLS files): those are in ``problems``, one line each, for the
    caller to report after the listing.

    Raises:
        ConfigError: the fleet directory or fleet.yaml is missing or malformed.
    """
    problems: list[str] = []
    fleet = load_fleet(fleet_dir, problems)
    pubs: dict[str, str] = {}
    unreadable: list[str] = []
    # keys/ (or keys/robots/) that is a file is one problem, already in *problems*: not
    # also every key file in it "not found".
    keys_dir = fleet_dir / keystore.KEYS_DIR
    keys_broken = not_a_directory(keys_dir)
    robot_keys_broken = keys_broken or not_a_directory(keys_dir / "robots")
    for robot in fleet.robots:
        if robot_keys_broken:
            unreadable.append(robot.name)
            continue
        try:
            if (rk := existing_robot_keys(fleet_dir, robot.name)) is not None:
                pubs[robot.name] = public_key(rk.private_key, f"key of robot {robot.name}")
        except ConfigError as exc:
            unreadable.append(robot.name)
            problems.append(str(exc))
    server_pub: str | None = None
    try:
        if not keys_broken:
            server_pub = public_key(keystore.load_server_key(fleet_dir), "server key")
    except ConfigError as exc:
        problems.insert(0, str(exc))  # the fleet's own key first: every robot needs it
    return FleetInfo(fleet_dir, fleet, server_pub, pubs, tuple(unreadable), tuple(problems))


def server_public_key(fleet_dir: Path) -> str:
    """Return the server's WireGuard public key."""
    return public_key(keystore.load_server_key(fleet_dir), "server key")


def robot_address(fleet_dir: Path, name: str) -> IPv4Address:
    """Return robot *name*'s VPN address (for tools such as ``fleetctl demo``).

    Raises:
        ConfigError: there is no such robot.
    """
    robot = load_fleet(fleet_dir).robot(name)
    if robot is None:
        raise ConfigError(f"robot {name!r} is not in {fleet_file(fleet_dir)}")
    return robot.ip
