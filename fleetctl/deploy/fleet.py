"""The fleet model (``fleet.yaml``, the one source of truth) and its load/save.

Everything ``fleetctl`` renders (WireGuard configs, the auth map, server and client
configs) is a pure function of a :class:`Fleet` and the key files beside ``fleet.yaml``.
"""

from __future__ import annotations

import enum
import ipaddress
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, replace
from ipaddress import IPv4Address, IPv4Network
from pathlib import Path

import yaml

from fleetctl.client.config import TfSpec, location_problem
from fleetctl.deploy.fleetrecording import (
    FleetRecording,
    build_recording,
    check_recording,
    dump_recording,
)
from fleetctl.deploy.msgtypes import NO_MSG_TYPES, FleetMsgTypes, load_msg_types
from fleetctl.deploy.topics import (
    DEFAULT_PUBLISH,
    PublishTopic,
    SubscribeTopic,
    build_publish,
    build_subscribe,
    build_tf,
    check_publish,
    check_regex,
    check_subscribe,
    check_tf,
    check_topic,
    check_type,
    dump_publish,
    dump_subscribe,
    dump_tf,
)
from fleetctl.deploy.yamlnodes import Document, FieldPath, FleetInvalid, shown
from fleetctl.errors import ConfigError
from fleetctl.smallfile import read_small_text

__all__ = ["FleetInvalid"]  # defined beside Document, raised and re-exported here

FLEET_FILE = "fleet.yaml"
FORMAT_VERSION = 1
DEFAULT_SUBNET = "10.8.0.0/24"
DEFAULT_SERVER_PORT = 8080
DEFAULT_WIREGUARD_PORT = 51820
DEFAULT_HTTPS_PORT = 8443
# Relay replicas `fleetctl up --replicas` deploys at most (fleetctl.deploy.replicas).
MAX_RELAY_REPLICAS = 8
# WireGuard's default 1420 assumes a 1500-byte path; LTE carriers often give 1428-1450 or
# less after their own tunnelling. 1280 is the IPv6 minimum and works on every path.
DEFAULT_MTU_BYTES = 1280
MIN_MTU_BYTES = 576
MAX_MTU_BYTES = 9000
# Names end up in file names, comments of every generated file, WireGuard's INI and
# systemd units: short, ASCII, and nothing any of those formats gives a meaning to.
MAX_NAME_CHARS = 63  # a fleet's or a robot's name (a DNS label's limit)
MAX_EMAIL_CHARS = 254  # RFC 5321's limit on a forward path
MAX_HOST_CHARS = 253
# ROS_DOMAIN_ID: 0..232 is what every RMW maps to valid UDP ports (ROS 2 docs, "The ROS
# DOMAIN ID"); 0 is ROS's own default.
DEFAULT_ROS_DOMAIN_ID = 0
MAX_ROS_DOMAIN_ID = 232
DEFAULT_RMW_IMPLEMENTATION = "rmw_fastrtps_cpp"
RMW_IMPLEMENTATIONS = ("rmw_fastrtps_cpp", "rmw_cyclonedds_cpp", "rmw_connextdds",
                       "rmw_zenoh_cpp")

# A ROS 2 name token: letters, digits, underscores, not starting with a digit, no "__"
# (rcl reserves repeated underscores). A robot name is one namespace segment.
_SEGMENT = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
_RELATIVE_TOPIC = re.compile(r"[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*")
_TYPE = re.compile(r"[A-Za-z][A-Za-z0-9_]*/(msg/)?[A-Za-z][A-Za-z0-9_]*")
# A fleet name: ASCII letters, digits, '.', '_' and '-', starting with a letter or digit.
_FLEET_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
# ASCII only (str.isdigit() and int() take any digits), and no leading zero: `host:01`
# would be written as is into wg0.conf's Endpoint while fleetctl reads port 1.
_PORT = re.compile(r"[1-9][0-9]{0,4}")
_SHA256 = re.compile(r"[0-9a-f]{64}")
_HOST = re.compile(r"[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?|\[[0-9A-Fa-f:.]+\]")


class Role(enum.Enum):
    """What a user may do.

    viewer: receive everything robots publish, send nothing. operator: viewer plus send
    every robot's command topics. admin: send and receive every topic. A viewer or an
    operator may be scoped to some robots (:attr:`User.robots`).
    """

    VIEWER = "viewer"
    OPERATOR = "operator"
    ADMIN = "admin"


@dataclass(frozen=True)
class CommandTopic:
    """A topic the fleet sends to a robot: ``/<robot>/<topic>``, republished as ``/<topic>``."""

    topic: str  # relative, e.g. "goal_pose"
    type: str  # ROS 2 type, e.g. "geometry_msgs/msg/PoseStamped"


DEFAULT_COMMAND_TOPICS: tuple[CommandTopic, ...] = (
    CommandTopic("goal_pose", "geometry_msgs/msg/PoseStamped"),
    CommandTopic("initialpose", "geometry_msgs/msg/PoseWithCovarianceStamped"),
)


@dataclass(frozen=True)
class Robot:
    """One robot: its VPN address and what it may send and receive beyond its own topics.

    Attributes:
        name: one ROS namespace segment; its topics are ``/<name>/...``.
        ip: its WireGuard address (the server identifies it by this source address).
        mtu_bytes: MTU of its WireGuard interface.
        command_topics: topics operators send it (it may receive ``/<name>/<topic>``).
        extra_send: more RE2 full-match topic regexes it may send (e.g. to another robot).
        extra_receive: more RE2 full-match topic regexes it may receive.
        publish: local topics it sends; ``None`` (no ``publish`` in fleet.yaml): the
            default set :data:`~fleetctl.deploy.topics.DEFAULT_PUBLISH`.
        subscribe: fleet topics it receives and republishes, beyond its command topics.
        battery_topic: its local ``sensor_msgs/msg/BatteryState`` topic, or ``None``.
        location: where it is, as people name it (its status's ``location``, the page's
            Location column); ``""``: not said.
        tf: its TF republisher (local ``/tf`` and ``/tf_static`` sent throttled as
            ``/<name>/tf`` and latched ``/<name>/tf_static``); ``None``: no TF.
        ros_domain_id: the ``ROS_DOMAIN_ID`` its ROS 2 graph uses (0..232).
        rmw_implementation: the ``RMW_IMPLEMENTATION`` it runs (one of
            :data:`RMW_IMPLEMENTATIONS`).
    """

    name: str
    ip: IPv4Address
    mtu_bytes: int = DEFAULT_MTU_BYTES
    command_topics: tuple[CommandTopic, ...] = DEFAULT_COMMAND_TOPICS
    extra_send: tuple[str, ...] = ()
    extra_receive: tuple[str, ...] = ()
    ros_domain_id: int = DEFAULT_ROS_DOMAIN_ID
    rmw_implementation: str = DEFAULT_RMW_IMPLEMENTATION
    publish: tuple[PublishTopic, ...] | None = None
    subscribe: tuple[SubscribeTopic, ...] = ()
    battery_topic: str | None = None
    location: str = ""
    tf: TfSpec | None = None

    @property
    def publish_topics(self) -> tuple[PublishTopic, ...]:
        """What it publishes: its ``publish`` list, or the default set."""
        return DEFAULT_PUBLISH if self.publish is None else self.publish


@dataclass(frozen=True)
class User:
    """A person, signed in with a token whose SHA-256 (hex) is all that is stored.

    Attributes:
        email: who (compared without case for duplicates).
        role: what they may do.
        token_sha256: the SHA-256 of their token, 64 lowercase hex digits.
        robots: the robots a viewer or an operator sees and commands, by name, in the
            order given (at least one, each a robot of the fleet); ``None``: every robot,
            those added later too. An admin has none: an admin is everything.
    """

    email: str
    role: Role
    token_sha256: str
    robots: tuple[str, ...] | None = None


@dataclass(frozen=True)
class TlsFiles:
    """The operator's own certificate and key for the HTTPS port (``tls:`` in fleet.yaml).

    Attributes:
        cert: PEM certificate (chain) path as written: absolute, or relative to the fleet
            directory.
        key: PEM private key path, the same way.
    """

    cert: str
    key: str

    def paths(self, fleet_dir: Path) -> tuple[Path, Path]:
        """Return the absolute certificate and key paths (``..`` folded away)."""
        cert, key = (Path(os.path.normpath((fleet_dir / p).absolute()))
                     for p in (self.cert, self.key))
        return cert, key


@dataclass(frozen=True)
class Fleet:
    """The whole fleet.

    Attributes:
        name: a label for the fleet (one printable line).
        endpoint: ``HOST:PORT`` robots reach the server's WireGuard on; ``None``: not
            known yet (robots' WireGuard configs then have no ``Endpoint``; see
            :func:`require_endpoint`).
        subnet: the VPN subnet; robots get a /32 inside it.
        server_ip: the server's VPN address (inside *subnet*).
        server_port: TCP port of the fleet server's WebSocket (plain ws://, inside the tunnel).
        wireguard_port: UDP port the server's WireGuard listens on.
        robots: in the order they were added.
        users: in the order they were added.
        https_port: TCP port of the one HTTPS listener people use (web page and wss://).
        tls: the operator's certificate and key; ``None``: a self-signed one that
            fleetctl generates (``server/tls/cert.pem``, ``keys/tls.key``).
        relay_replicas: relays the server host runs (``fleetctl up --replicas N`` records
            it): replica *i* listens on ``server_port`` + *i* and ``https_port`` + *i*, and
            every robot's ``client.yaml`` lists every replica's URL, so that a bundle
            exported from it fails over between them (docs/deploy.md).
        recording: what the server records (fleet.yaml ``recording:``); ``None``: nothing.
        msg_types: the fleet's own message definitions (``FLEET/msg_types``, not part of
            fleet.yaml); topics may name their types. Empty when fleet.yaml is checked
            without its directory.
    """

    name: str
    endpoint: str | None
    subnet: IPv4Network
    server_ip: IPv4Address
    server_port: int = DEFAULT_SERVER_PORT
    wireguard_port: int = DEFAULT_WIREGUARD_PORT
    robots: tuple[Robot, ...] = ()
    users: tuple[User, ...] = ()
    https_port: int = DEFAULT_HTTPS_PORT
    tls: TlsFiles | None = None
    relay_replicas: int = 1
    recording: FleetRecording | None = None
    msg_types: FleetMsgTypes = NO_MSG_TYPES

    def robot(self, name: str) -> Robot | None:
        """Return the robot called *name*, or ``None``."""
        return next((r for r in self.robots if r.name == name), None)

    def user(self, email: str) -> User | None:
        """Return the user with *email*, or ``None``."""
        return next((u for u in self.users if u.email == email), None)


# --- validation ------------------------------------------------------------------------


def check_robot_name(name: str) -> None:
    """Raise :class:`FleetInvalid` unless *name* is a valid ROS namespace segment of at
    most :data:`MAX_NAME_CHARS` characters."""
    if len(name) > MAX_NAME_CHARS:
        raise FleetInvalid(("name",), f"robot name {shown(name)} is {len(name)} characters "
                           f"long (at most {MAX_NAME_CHARS})")
    if not _SEGMENT.fullmatch(name) or "__" in name:
        raise FleetInvalid(
            ("name",),
            f"robot name {shown(name)} is not a ROS namespace segment "
            "(ASCII letters, digits and single underscores, starting with a letter)",
        )


def check_fleet_name(name: str) -> None:
    """Raise :class:`FleetInvalid` unless *name* is a valid fleet name: 1 to
    :data:`MAX_NAME_CHARS` ASCII letters, digits, ``.``, ``_`` or ``-``, starting with a
    letter or a digit (it lands in comments of every generated file)."""
    if len(name) > MAX_NAME_CHARS:
        raise FleetInvalid(("name",), f"fleet name {shown(name)} is {len(name)} characters "
                           f"long (at most {MAX_NAME_CHARS})")
    if not _FLEET_NAME.fullmatch(name):
        raise FleetInvalid(("name",), f"fleet name {shown(name)} must be ASCII letters, "
                           "digits, '.', '_' or '-', starting with a letter or a digit")


def default_fleet_name(directory: Path) -> str:
    """A valid fleet name made from a directory's name (``fleet`` if nothing is left)."""
    text = re.sub(r"[^A-Za-z0-9._-]+", "-", directory.resolve().name)
    return text.lstrip("._-")[:MAX_NAME_CHARS].rstrip("._-") or "fleet"


def check_email(email: str) -> None:
    """Raise :class:`FleetInvalid` unless *email* looks like an address: one ``@`` with
    something on both sides, printable, no whitespace, at most :data:`MAX_EMAIL_CHARS`
    characters (any script: it is stored and compared, never sent)."""
    if len(email) > MAX_EMAIL_CHARS:
        raise FleetInvalid(("email",), f"{shown(email)} is {len(email)} characters long "
                           f"(at most {MAX_EMAIL_CHARS})")
    local, at, domain = email.partition("@")
    if not (at and local and domain and "@" not in domain and email.isprintable()
            and " " not in email):
        raise FleetInvalid(("email",), f"{shown(email)} is not an email address (one '@', "
                           "printable, no spaces)")


def parse_endpoint(endpoint: str) -> tuple[str, int]:
    """Split ``HOST:PORT`` (``[v6]:PORT`` for IPv6) and check both parts.

    Raises:
        FleetInvalid: naming the field ``endpoint``.
    """
    host, sep, port = endpoint.rpartition(":")
    if (not sep or len(host) > MAX_HOST_CHARS or not _HOST.fullmatch(host)
            or not _host_is_valid(host)
            or not _PORT.fullmatch(port) or not 0 < int(port) < 65536):
        raise FleetInvalid(("endpoint",), f"expected HOST:PORT (ASCII, port 1..65535 "
                           f"without a leading zero), got {shown(endpoint)}")
    return host, int(port)


def _host_is_valid(host: str) -> bool:
    """True for ``[IPv6]``, a dotted-quad IPv4 address, or a DNS name whose labels are 1..63
    characters (*host* already matched :data:`_HOST`): what WireGuard's ``Endpoint`` and
    the certificate's subject names can use."""
    if host.startswith("["):
        try:
            ipaddress.IPv6Address(host[1:-1])
        except ValueError:
            return False
        return True
    labels = host.split(".")
    if all(label.isdigit() for label in labels):  # looks like an IPv4 address: must be one
        try:
            IPv4Address(host)
        except ValueError:
            return False
        return True
    return all(0 < len(label) <= 63 and not label.startswith("-") and not label.endswith("-")
               for label in labels)


def _check_host_ip(fleet: Fleet, ip: IPv4Address, path: FieldPath) -> None:
    if ip not in fleet.subnet:
        raise FleetInvalid(path, f"{ip} is outside the fleet subnet {fleet.subnet}")
    if ip in (fleet.subnet.network_address, fleet.subnet.broadcast_address):
        raise FleetInvalid(path, f"{ip} is the network or broadcast address of {fleet.subnet}")


def _check_robot(fleet: Fleet, i: int, robot: Robot, seen: dict[object, str]) -> None:
    path: FieldPath = ("robots", i)
    try:
        check_robot_name(robot.name)
    except FleetInvalid as exc:
        raise FleetInvalid((*path, "name"), str(exc)) from None
    if ("name", robot.name) in seen:
        raise FleetInvalid((*path, "name"), f"duplicate robot name {robot.name!r}", conflict=True)
    if (other_name := seen.get(("name-case", robot.name.lower()))) is not None:
        # keys/robots/NAME.key, robots/NAME/: one file on a case-insensitive file system
        # (macOS, Windows), where one robot's keys would replace the other's.
        raise FleetInvalid((*path, "name"), f"robot name {robot.name!r} differs from robot "
                           f"{other_name!r} only in case: their files would be the same on "
                           "a case-insensitive file system", conflict=True)
    _check_host_ip(fleet, robot.ip, (*path, "ip"))
    if robot.ip == fleet.server_ip:
        raise FleetInvalid((*path, "ip"), f"{robot.ip} is the server's address", conflict=True)
    if ("ip", robot.ip) in seen:
        other = seen[("ip", robot.ip)]
        raise FleetInvalid((*path, "ip"), f"{robot.ip} is already used by robot {other!r}",
                           conflict=True)
    seen[("name", robot.name)] = seen[("ip", robot.ip)] = robot.name
    seen[("name-case", robot.name.lower())] = robot.name
    _check_robot_topics(robot, path, fleet.msg_types)


def _check_robot_topics(robot: Robot, path: FieldPath, own: FleetMsgTypes) -> None:
    if not MIN_MTU_BYTES <= robot.mtu_bytes <= MAX_MTU_BYTES:
        raise FleetInvalid((*path, "mtu_bytes"),
                           f"must be between {MIN_MTU_BYTES} and {MAX_MTU_BYTES}")
    taken: dict[str, str] = {}
    for j, cmd in enumerate(robot.command_topics):
        if not _RELATIVE_TOPIC.fullmatch(cmd.topic) or "__" in cmd.topic:
            raise FleetInvalid((*path, "command_topics", j, "topic"),
                               f"{cmd.topic!r} is not a relative ROS topic name")
        if not _TYPE.fullmatch(cmd.type):
            raise FleetInvalid((*path, "command_topics", j, "type"),
                               f"{cmd.type!r} is not a ROS type name (pkg/msg/Name)")
        check_type(cmd.type, (*path, "command_topics", j, "type"), own)
        taken[f"remote /{robot.name}/{cmd.topic}"] = f"command_topics[{j}]"
        taken[f"local /{cmd.topic}"] = f"command_topics[{j}]"
    for field_name in ("extra_send", "extra_receive"):
        for j, pattern in enumerate(getattr(robot, field_name)):
            check_regex(pattern, (*path, field_name, j))
    if robot.publish is not None:
        check_publish(robot.publish, (*path, "publish"), own)
    check_tf(robot.tf, robot.publish_topics, path)
    check_subscribe(robot.subscribe, taken, (*path, "subscribe"), own)
    if robot.battery_topic is not None:
        check_topic(robot.battery_topic, (*path, "battery_topic"))
    problem = location_problem(robot.location)
    if problem is not None:
        raise FleetInvalid((*path, "location"), problem)
    _check_ros_environment(robot, path)


def _check_ros_environment(robot: Robot, path: FieldPath) -> None:
    if not 0 <= robot.ros_domain_id <= MAX_ROS_DOMAIN_ID:
        raise FleetInvalid((*path, "ros_domain_id"),
                           f"must be between 0 and {MAX_ROS_DOMAIN_ID}, got {robot.ros_domain_id}")
    if robot.rmw_implementation not in RMW_IMPLEMENTATIONS:
        raise FleetInvalid((*path, "rmw_implementation"),
                           f"unknown RMW implementation {robot.rmw_implementation!r} "
                           f"(expected one of {', '.join(RMW_IMPLEMENTATIONS)})")


def _check_user(fleet: Fleet, i: int, user: User, seen: set[str]) -> None:
    path: FieldPath = ("users", i)
    try:
        check_email(user.email)
    except FleetInvalid as exc:
        raise FleetInvalid((*path, "email"), str(exc)) from None
    if user.email in seen:
        raise FleetInvalid((*path, "email"), f"duplicate user {shown(user.email)}",
                           conflict=True)
    if other := next((e for e in seen if e.casefold() == user.email.casefold()), None):
        # Mail does not tell them apart: one person, two tokens, and `remove-user` of one
        # spelling leaves the other working.
        raise FleetInvalid((*path, "email"), f"user {shown(user.email)} differs from user "
                           f"{shown(other)} only in case", conflict=True)
    seen.add(user.email)
    if not _SHA256.fullmatch(user.token_sha256):
        raise FleetInvalid((*path, "token_sha256"), "expected 64 lowercase hex digits")
    if user.robots is not None:
        check_user_robots(fleet, user.role, user.robots, (*path, "robots"))


def check_user_robots(fleet: Fleet, role: Role, robots: tuple[str, ...],
                      path: FieldPath) -> None:
    """Raise :class:`FleetInvalid` (at *path*, or at the item) unless *robots* is a scope
    *role* may have: not an admin's, not empty, no name twice, every name a robot of
    *fleet*."""
    if role is Role.ADMIN:
        raise FleetInvalid(path, "an admin may use every robot and cannot be scoped to "
                           "some: remove the field, or make the user a viewer or an operator")
    if not robots:
        # Refused rather than read as "no robot": a token that shows nothing is a user to
        # remove, and an empty list reads too easily as "no restriction".
        raise FleetInvalid(path, "an empty list: name at least one robot, or leave the "
                           "field out for every robot")
    for j, name in enumerate(robots):
        if name in robots[:j]:
            raise FleetInvalid((*path, j), f"robot {shown(name)} is listed twice")
        if fleet.robot(name) is None:
            known = ", ".join(r.name for r in fleet.robots) or "none"
            raise FleetInvalid((*path, j), f"no robot {shown(name)} in the fleet "
                               f"(its robots: {known})")


def validate(fleet: Fleet) -> None:
    """Check every rule a fleet must satisfy.

    Raises:
        FleetInvalid: the first problem found, with the field path it concerns.
    """
    check_fleet_name(fleet.name)
    if fleet.endpoint is not None:
        parse_endpoint(fleet.endpoint)
    if fleet.https_port == fleet.server_port:
        raise FleetInvalid(("https_port",), f"{fleet.https_port} is also server_port "
                           "(the plain ws:// port); the two listeners need two ports")
    _check_replica_ports(fleet)
    if fleet.tls is not None:
        _check_tls_paths(fleet.tls)
    if fleet.recording is not None:
        check_recording(fleet.recording)
    if fleet.subnet.num_addresses < 4:
        raise FleetInvalid(("subnet",), f"{fleet.subnet} is too small (at most /30)")
    _check_subnet_range(fleet.subnet)
    _check_host_ip(fleet, fleet.server_ip, ("server_ip",))
    seen: dict[object, str] = {}
    for i, robot in enumerate(fleet.robots):
        _check_robot(fleet, i, robot, seen)
    emails: set[str] = set()
    for i, user in enumerate(fleet.users):
        _check_user(fleet, i, user, emails)


# Each robot routes the whole fleet subnet through its tunnel (AllowedIPs): a larger one
# would take routes the robot needs (0.0.0.0/0 took all of its traffic, its default route
# included, which docs/operator.md promises never happens).
MIN_SUBNET_PREFIX = 8
_NOT_UNICAST = (IPv4Network("0.0.0.0/8"), IPv4Network("224.0.0.0/4"),
                IPv4Network("240.0.0.0/4"))


def _check_subnet_range(subnet: IPv4Network) -> None:
    if subnet.prefixlen < MIN_SUBNET_PREFIX:
        raise FleetInvalid(("subnet",), f"{subnet} is too large (at least /{MIN_SUBNET_PREFIX}):"
                           " every robot routes the fleet subnet through its tunnel, and "
                           "this one would take its other routes; use a private range such "
                           "as 10.8.0.0/24")
    if bad := next((n for n in _NOT_UNICAST if subnet.overlaps(n)), None):
        raise FleetInvalid(("subnet",), f"{subnet} is in {bad}, not unicast addresses an "
                           "interface can have; use a private range such as 10.8.0.0/24")


def _check_replica_ports(fleet: Fleet) -> None:
    """Replica *i* listens on server_port + *i* and https_port + *i*: both runs of ports
    must exist and must not overlap."""
    n = fleet.relay_replicas
    if not 1 <= n <= MAX_RELAY_REPLICAS:
        raise FleetInvalid(("relay_replicas",), f"expected 1 to {MAX_RELAY_REPLICAS}, got {n}")
    if n == 1:
        return
    for key, first in (("server_port", fleet.server_port), ("https_port", fleet.https_port)):
        if first + n - 1 > 65535:
            raise FleetInvalid((key,), f"{n} relay replicas need ports {first} to "
                               f"{first + n - 1}, past 65535")
    plain = range(fleet.server_port, fleet.server_port + n)
    https = range(fleet.https_port, fleet.https_port + n)
    if plain.start < https.stop and https.start < plain.stop:
        raise FleetInvalid(("relay_replicas",), f"{n} relay replicas listen on server_port "
                           f"{plain.start}-{plain.stop - 1} and https_port "
                           f"{https.start}-{https.stop - 1}: the two runs overlap")


def _check_tls_paths(tls: TlsFiles) -> None:
    for field_name, value in (("cert", tls.cert), ("key", tls.key)):
        if not value.strip() or not value.isprintable():
            raise FleetInvalid(("tls", field_name), f"not a file path: {shown(value)}")


def require_endpoint(fleet: Fleet, fleet_dir: Path) -> str:
    """Return the fleet's endpoint, for what cannot work without one (a robot bundle).

    Raises:
        ConfigError: ``FLEET/fleet.yaml: endpoint: not set; run ...`` naming the fix.
    """
    if fleet.endpoint is None:
        raise ConfigError(f"{fleet_file(fleet_dir)}: endpoint: not set; run "
                          "`fleetctl set-endpoint HOST:PORT` (where robots reach the server's "
                          "WireGuard)")
    return fleet.endpoint


def next_free_ip(fleet: Fleet) -> IPv4Address:
    """Return the lowest address of the subnet not used by the server or a robot.

    Raises:
        FleetInvalid: if the subnet is full (a conflict).
    """
    used = {fleet.server_ip, *(r.ip for r in fleet.robots)}
    for host in fleet.subnet.hosts():
        if host not in used:
            return host
    raise FleetInvalid(("subnet",), f"the subnet {fleet.subnet} is full", conflict=True)


def parse_subnet(text: str, path: FieldPath = ("subnet",)) -> IPv4Network:
    """Parse an IPv4 subnet in CIDR form (host bits must be zero)."""
    try:
        net = ipaddress.ip_network(text, strict=True)
    except ValueError as exc:
        raise FleetInvalid(path, f"not a subnet in CIDR form: {exc}") from None
    if not isinstance(net, IPv4Network):
        raise FleetInvalid(path, "only IPv4 subnets are supported")
    return net


def parse_ip(text: str, path: FieldPath) -> IPv4Address:
    """Parse an IPv4 address."""
    try:
        return IPv4Address(text)
    except ValueError:
        raise FleetInvalid(path, f"not an IPv4 address: {text!r}") from None


# --- load ------------------------------------------------------------------------------


def fleet_file(fleet_dir: Path) -> Path:
    """Return the path of ``fleet.yaml`` in *fleet_dir*."""
    return fleet_dir / FLEET_FILE


def require_fleet_dir(fleet_dir: Path) -> None:
    """Refuse a fleet directory that is not one.

    Raises:
        ConfigError: *fleet_dir* does not exist or is not a directory.
    """
    if not fleet_dir.is_dir():
        what = "exists and is not a directory" if os.path.lexists(fleet_dir) else "does not exist"
        raise ConfigError(f"fleet directory {fleet_dir} {what} "
                          "(create one with 'fleetctl init', or set --fleet / FLEET_DIR)")


# The directories fleetctl keeps in a fleet directory, and what each holds (said when one
# is something else): a regular file named keys/ made every robot's key files "not found",
# and a file named server/ or robots/NAME a "cannot write" (exit 5) of the first file in it.
# msg_types/ is checked where it is read (fleetctl.deploy.msgtypes).
_FLEET_DIRECTORIES: tuple[tuple[str, str], ...] = (
    ("keys", "the fleet's WireGuard private keys: move the file away and restore the "
     "directory from a backup of the fleet directory"),
    ("keys/robots", "the robots' WireGuard keys: move the file away and restore the "
     "directory from a backup of the fleet directory"),
    ("server", "the server's generated configs and TLS certificate: move the file away, "
     "restore server/tls from a backup if you had one, then run `fleetctl render`"),
    ("server/wireguard", "the server's WireGuard config: move the file away, then run "
     "`fleetctl render`"),
    ("server/tls", "the server's HTTPS certificate: move the file away, restore the directory "
     "from a backup or run `fleetctl render` for a new self-signed one"),
    ("robots", "the robots' generated configs: move the file away, then run `fleetctl render`"),
    (".compose", "the deployment's files, made by `fleetctl up`: move the file away, `up` "
     "makes the directory again"),
)


def not_a_directory(path: Path) -> bool:
    """Whether *path* exists (a dangling symbolic link too) and is not a directory."""
    return os.path.lexists(path) and not path.is_dir()


def directory_problems(fleet_dir: Path, robot_names: Iterable[str] = ()) -> list[str]:
    """One line per directory of the fleet that exists but is not a directory (a
    symbolic link to a directory is one), naming it and what it should hold."""
    expected = [*_FLEET_DIRECTORIES, *((f"robots/{name}", f"the configs made for robot "
                                        f"{name!r}: move the file away, then run `fleetctl "
                                        "render`") for name in robot_names)]
    problems = []
    for relative, holds in expected:
        path = fleet_dir / relative
        if not_a_directory(path):
            what = (f"a symbolic link to {os.readlink(path)}" if path.is_symlink()
                    else "a file")
            problems.append(f"{path}: not a directory but {what} (it holds {holds})")
    return problems


def load_fleet(fleet_dir: Path, file_problems: list[str] | None = None) -> Fleet:
    """Load and validate ``fleet_dir/fleet.yaml``.

    Args:
        fleet_dir: The fleet directory.
        file_problems: When given, a file fleet.yaml points at (``tls``) that is missing or
            bad is appended to it (the error's one line) instead of raised: for ``list``,
            which shows what it can.

    Raises:
        ConfigError: the directory or file is missing, or the file is malformed or invalid;
            the message names the file, the line and the field.
    """
    require_fleet_dir(fleet_dir)
    path = fleet_file(fleet_dir)
    try:
        text = read_small_text(path)
    except FileNotFoundError:
        if path.is_symlink():
            raise ConfigError(f"{path}: is a symbolic link to {os.readlink(path)}, which does "
                              "not exist") from None
        raise ConfigError(f"{path}: not found: {fleet_dir} is not a fleet directory "
                          "(create one with 'fleetctl init')") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: cannot read: not UTF-8 text") from None
    fleet = parse_fleet(path, text, fleet_dir, file_problems)
    problems = directory_problems(fleet_dir, (r.name for r in fleet.robots))
    if problems and file_problems is None:
        raise ConfigError(problems[0] if len(problems) == 1 else f"{len(problems)} problems: "
                          + " ".join(f"[{i}] {p}" for i, p in enumerate(problems, 1)))
    if file_problems is not None:
        file_problems.extend(problems)
    return fleet


def parse_fleet(path: Path, text: str, fleet_dir: Path | None = None,
                file_problems: list[str] | None = None) -> Fleet:
    """Parse and validate fleet.yaml text.

    Args:
        path: the file, only used in error messages.
        text: its content.
        fleet_dir: when given, files fleet.yaml points at (``tls``) are checked too,
            relative to this directory, and its ``msg_types`` (the fleet's own message
            types) are read; ``None`` checks the text alone.
        file_problems: see :func:`load_fleet`.

    Raises:
        ConfigError: ``FILE:LINE: FIELD: problem``, or a problem of a ``msg_types`` file.
    """
    msg_types = load_msg_types(fleet_dir) if fleet_dir is not None else NO_MSG_TYPES
    doc = Document(path, text)
    try:
        fleet = replace(_build_fleet(doc), msg_types=msg_types)
        validate(fleet)
    except FleetInvalid as exc:
        raise doc.error(exc.path, str(exc)) from None
    if fleet_dir is not None and fleet.tls is not None:
        from fleetctl.deploy.tls import check_operator_files

        try:
            check_operator_files(*fleet.tls.paths(fleet_dir))
        except FleetInvalid as exc:
            error = doc.error(exc.path, str(exc))
            if file_problems is None:
                raise error from None
            file_problems.append(str(error))
    return fleet


def _build_fleet(doc: Document) -> Fleet:
    f = doc.mapping(doc.root, (), ["version", "name", "subnet", "server_ip"],
                    ["endpoint", "server_port", "wireguard_port", "https_port", "tls", "robots",
                     "users", "relay_replicas", "recording"])
    version = doc.integer(f["version"], ("version",), 1, 1_000_000)
    if version != FORMAT_VERSION:
        raise FleetInvalid(("version",), f"unsupported version {version} "
                           f"(this fleetctl reads version {FORMAT_VERSION})")
    name = doc.string(f["name"], ("name",))
    endpoint = doc.optional_string(f["endpoint"], ("endpoint",)) if "endpoint" in f else None
    subnet = parse_subnet(doc.string(f["subnet"], ("subnet",)))
    server_ip = parse_ip(doc.string(f["server_ip"], ("server_ip",)), ("server_ip",))
    robot_nodes = doc.sequence(f["robots"], ("robots",)) if "robots" in f else []
    user_nodes = doc.sequence(f["users"], ("users",)) if "users" in f else []
    return Fleet(
        name=name,
        endpoint=endpoint,
        subnet=subnet,
        server_ip=server_ip,
        server_port=_port(doc, f, "server_port", DEFAULT_SERVER_PORT),
        wireguard_port=_port(doc, f, "wireguard_port", DEFAULT_WIREGUARD_PORT),
        robots=tuple(_build_robot(doc, n, ("robots", i)) for i, n in enumerate(robot_nodes)),
        users=tuple(_build_user(doc, n, ("users", i)) for i, n in enumerate(user_nodes)),
        https_port=_port(doc, f, "https_port", DEFAULT_HTTPS_PORT),
        tls=_build_tls(doc, f["tls"]) if "tls" in f and not doc.is_null(f["tls"]) else None,
        relay_replicas=(doc.integer(f["relay_replicas"], ("relay_replicas",), 1,
                                    MAX_RELAY_REPLICAS) if "relay_replicas" in f else 1),
        recording=build_recording(doc, f["recording"]) if "recording" in f else None,
    )


def _build_tls(doc: Document, node: yaml.Node) -> TlsFiles:
    f = doc.mapping(node, ("tls",), ["cert", "key"], [])
    return TlsFiles(doc.string(f["cert"], ("tls", "cert")), doc.string(f["key"], ("tls", "key")))


def _port(doc: Document, f: dict[str, yaml.Node], key: str, default: int) -> int:
    return doc.integer(f[key], (key,), 1, 65535) if key in f else default


def _build_robot(doc: Document, node: yaml.Node, path: FieldPath) -> Robot:
    f = doc.mapping(node, path, ["name", "ip"],
                    ["mtu_bytes", "command_topics", "extra_send", "extra_receive",
                     "ros_domain_id", "rmw_implementation", "publish", "subscribe",
                     "battery_topic", "location", "tf"])
    cmds = DEFAULT_COMMAND_TOPICS
    if "command_topics" in f:
        cpath = (*path, "command_topics")
        cmds = tuple(_build_command(doc, n, (*cpath, j))
                     for j, n in enumerate(doc.sequence(f["command_topics"], cpath)))
    return Robot(
        name=doc.string(f["name"], (*path, "name")),
        ip=parse_ip(doc.string(f["ip"], (*path, "ip")), (*path, "ip")),
        mtu_bytes=(doc.integer(f["mtu_bytes"], (*path, "mtu_bytes"), MIN_MTU_BYTES, MAX_MTU_BYTES)
                   if "mtu_bytes" in f else DEFAULT_MTU_BYTES),
        command_topics=cmds,
        extra_send=_strings(doc, f, "extra_send", path),
        extra_receive=_strings(doc, f, "extra_receive", path),
        ros_domain_id=(doc.integer(f["ros_domain_id"], (*path, "ros_domain_id"), 0,
                                   MAX_ROS_DOMAIN_ID)
                       if "ros_domain_id" in f else DEFAULT_ROS_DOMAIN_ID),
        rmw_implementation=(doc.string(f["rmw_implementation"], (*path, "rmw_implementation"))
                            if "rmw_implementation" in f else DEFAULT_RMW_IMPLEMENTATION),
        publish=(build_publish(doc, f["publish"], (*path, "publish"))
                 if "publish" in f and not doc.is_null(f["publish"]) else None),
        subscribe=(build_subscribe(doc, f["subscribe"], (*path, "subscribe"))
                   if "subscribe" in f else ()),
        battery_topic=(doc.optional_string(f["battery_topic"], (*path, "battery_topic"))
                       if "battery_topic" in f else None),
        location=doc.string(f["location"], (*path, "location")) if "location" in f else "",
        tf=build_tf(doc, f, path),
    )


def _build_command(doc: Document, node: yaml.Node, path: FieldPath) -> CommandTopic:
    f = doc.mapping(node, path, ["topic", "type"], [])
    return CommandTopic(doc.string(f["topic"], (*path, "topic")),
                        doc.string(f["type"], (*path, "type")))


def _strings(doc: Document, f: dict[str, yaml.Node], key: str, path: FieldPath) -> tuple[str, ...]:
    if key not in f:
        return ()
    p = (*path, key)
    return tuple(doc.string(n, (*p, j)) for j, n in enumerate(doc.sequence(f[key], p)))


def _build_user(doc: Document, node: yaml.Node, path: FieldPath) -> User:
    f = doc.mapping(node, path, ["email", "role", "token_sha256"], ["robots"])
    role_text = doc.string(f["role"], (*path, "role"))
    try:
        role = Role(role_text)
    except ValueError:
        raise FleetInvalid((*path, "role"), f"unknown role {role_text!r} "
                           f"(expected one of {', '.join(r.value for r in Role)})") from None
    return User(doc.string(f["email"], (*path, "email")), role,
                doc.string(f["token_sha256"], (*path, "token_sha256")),
                _user_robots(doc, f["robots"], (*path, "robots")) if "robots" in f else None)


def _user_robots(doc: Document, node: yaml.Node, path: FieldPath) -> tuple[str, ...]:
    if doc.is_null(node):
        # `robots:` with nothing after it: refused rather than read as every robot (a
        # list left to fill in later would widen the user to the whole fleet).
        raise FleetInvalid(path, "expected a list of robot names, got null (leave the "
                           "field out for every robot)")
    if isinstance(node, yaml.ScalarNode):
        raise FleetInvalid(path, f"expected a list of robot names such as [husky1, jackal2],"
                           f" got {shown(str(node.value))}")
    return tuple(doc.string(n, (*path, j)) for j, n in enumerate(doc.sequence(node, path)))


# --- save ------------------------------------------------------------------------------

_HEADER = (
    "# fleetctl fleet: the one source of truth. Edit it by hand or with fleetctl, then run\n"
    "# 'fleetctl render' to regenerate every config. Keys live in keys/ (never in here).\n"
    "# A robot without 'publish' sends the default topic set (docs/operator.md).\n"
)


def dump_fleet(fleet: Fleet) -> str:
    """Return the ``fleet.yaml`` text of *fleet* (deterministic: same fleet, same bytes)."""
    data = {
        "version": FORMAT_VERSION,
        "name": fleet.name,
        "endpoint": fleet.endpoint,
        "subnet": str(fleet.subnet),
        "server_ip": str(fleet.server_ip),
        "server_port": fleet.server_port,
        "wireguard_port": fleet.wireguard_port,
        "https_port": fleet.https_port,
        "tls": {"cert": fleet.tls.cert, "key": fleet.tls.key} if fleet.tls else None,
        # Only when set: a fleet with one relay keeps the bytes it had before the field.
        **({"relay_replicas": fleet.relay_replicas} if fleet.relay_replicas != 1 else {}),
        # Only when set, as relay_replicas.
        **({"recording": dump_recording(fleet.recording)} if fleet.recording else {}),
        "robots": [_dump_robot(r) for r in fleet.robots],
        "users": [_dump_user(u) for u in fleet.users],
    }
    return _HEADER + yaml.safe_dump(data, sort_keys=False, default_flow_style=False,
                                    allow_unicode=True, width=100)


def _dump_robot(robot: Robot) -> dict[str, object]:
    out: dict[str, object] = {
        "name": robot.name,
        "ip": str(robot.ip),
        "mtu_bytes": robot.mtu_bytes,
        "command_topics": [{"topic": c.topic, "type": c.type} for c in robot.command_topics],
        "extra_send": list(robot.extra_send),
        "extra_receive": list(robot.extra_receive),
        "ros_domain_id": robot.ros_domain_id,
        "rmw_implementation": robot.rmw_implementation,
    }
    if robot.publish is not None:  # absent means the default set, which may change
        out["publish"] = dump_publish(robot.publish)
    out["subscribe"] = dump_subscribe(robot.subscribe)
    out["battery_topic"] = robot.battery_topic
    if robot.location:  # absent: not said, and older fleets keep their bytes
        out["location"] = robot.location
    if robot.tf is not None:  # absent: no TF, and older fleets keep their bytes
        out["tf"] = dump_tf(robot.tf)
    return out


def _dump_user(user: User) -> dict[str, object]:
    out: dict[str, object] = {"email": user.email, "role": user.role.value}
    if user.robots is not None:  # absent: every robot, and older fleets keep their bytes
        out["robots"] = list(user.robots)
    out["token_sha256"] = user.token_sha256
    return out
