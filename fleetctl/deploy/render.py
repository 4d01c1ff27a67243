"""Render every artifact of a fleet from jinja2 templates (``StrictUndefined``).

Rendering is a pure function of the :class:`~fleetctl.deploy.fleet.Fleet` and its keys:
the same inputs give the same bytes, so re-rendering an unchanged fleet writes nothing.
Every value goes through the filter of its output format (``y`` YAML, ``wg`` WireGuard's
INI, ``sh`` shell, ``unit`` systemd, ``env`` env files, ``md`` Markdown, ``comment`` a
``#`` comment line); a value that skips it is an error (jinja's ``finalize``). Every
rendered file starts with its digest line
(:func:`fleetctl.deploy.files.stamp`), so hand edits are noticed before an overwrite.
"""

from __future__ import annotations

import functools
import json
import math
import re
import shlex
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import jinja2

from fleetctl.deploy import auth
from fleetctl.deploy.assets import asset_dir
from fleetctl.deploy.files import Plan, check_overwrite, stamp
from fleetctl.deploy.fleet import Fleet, Robot
from fleetctl.deploy.keys import public_key
from fleetctl.deploy.keystore import RobotKeys
from fleetctl.deploy.secrets import Secret
from fleetctl.deploy.tls import CERT_RELPATH, KEY_RELPATH
from fleetctl.errors import ConfigError, EnvironmentMissing

TEMPLATES_ENV = "FLEETCTL_TEMPLATES"  # overrides where templates/ is looked up


@dataclass(frozen=True)
class FleetKeys:
    """All key material a fleet's artifacts need."""

    server_private_key: Secret
    robots: Mapping[str, RobotKeys]

    def robot(self, name: str) -> RobotKeys:
        """Return robot *name*'s keys.

        Raises:
            ConfigError: if the fleet has no keys for it.
        """
        try:
            return self.robots[name]
        except KeyError:
            raise ConfigError(f"no keys for robot {name!r}") from None


@dataclass(frozen=True)
class Artifact:
    """One rendered file, its path relative to its root, and whether it holds a secret."""

    relpath: str
    text: str
    secret: bool = False
    hint: str = "change fleet.yaml instead"  # where its settings belong (hand-edit error)


def templates_dir() -> Path:
    """Return the ``templates/`` directory (``$FLEETCTL_TEMPLATES`` overrides)."""
    return asset_dir("templates")


class Escaped(str):
    """Text made safe for one output format by one of the filters below.

    Every ``{{ ... }}`` of a template must produce one (``finalize`` checks), so a value
    that skipped its format's filter is an error, not a file.
    """


def _one_line(text: str, fmt: str) -> str:
    # isprintable() is False for every line break (\n, \r, \x85, \u2028, \u2029), NUL and
    # other control or format characters, and lone surrogates.
    if not text.isprintable():
        raise ValueError(f"a {fmt} value must be one printable line: {text[:40]!r}")
    return text


def _yaml_char(c: str) -> str:
    if c in '"\\':
        return "\\" + c
    if " " <= c <= "~":
        return c
    # Everything else escaped: YAML's \uXXXX / \UXXXXXXXX (YAML 1.1 section 5.7), so no
    # line break (\n, \x85, \u2028) or control character reaches the file raw, and a
    # character beyond the BMP is one \U escape (never a surrogate pair, which a YAML
    # reader would return as two lone surrogates).
    return f"\\u{ord(c):04x}" if ord(c) <= 0xFFFF else f"\\U{ord(c):08x}"


_YAML_KEY = re.compile(r"[a-z][a-z0-9_]*")
_YAML_WORDS = {"y", "n", "yes", "no", "on", "off", "true", "false", "null"}


def yaml_scalar(value: object, key: bool = False) -> Escaped:
    """``y``: a scalar as a one-line YAML flow scalar (strings double-quoted, escaped);
    ``y(key=True)``: a mapping key, a bare lowercase word (a quoted key longer than 1024
    characters would not be a key at all).

    Raises:
        TypeError: not a str, int, float, bool or None.
        ValueError: a float that is not finite; a key that is not a plain word.
        jinja2.UndefinedError: *value* is undefined (``StrictUndefined``).
    """
    if isinstance(value, jinja2.Undefined):
        str(value)  # StrictUndefined raises here, naming the variable
    if key:
        if not (isinstance(value, str) and _YAML_KEY.fullmatch(value)
                and value not in _YAML_WORDS and len(value) <= 64):
            raise ValueError(f"not a plain YAML key: {str(value)[:40]!r}")
        return Escaped(value)
    if isinstance(value, str):
        return Escaped('"' + "".join(_yaml_char(c) for c in value) + '"')
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"not a finite number: {value}")
    if not isinstance(value, int | float | bool) and value is not None:
        raise TypeError(f"not a YAML scalar: {type(value).__name__}")
    return Escaped(json.dumps(value))


def wg_value(value: object) -> Escaped:
    """``wg``: a value for a WireGuard INI line (or a comment in one).

    wg-quick reads line by line and has no quoting: it cuts a line at its first ``#``,
    splits it at the first ``=`` and strips blanks. So the only defence is refusing what
    would change that: a line break (a new line, a new ``[Peer]``), a ``#``, surrounding
    blanks. Everything reaching these templates is validated (names, addresses, base64
    keys); this catches a slip.

    Raises:
        ValueError: such a value.
    """
    text = _one_line(str(value), "WireGuard config")
    if "#" in text or text != text.strip():
        raise ValueError(f"a WireGuard config value cannot hold '#' or surrounding blanks: "
                         f"{text[:40]!r}")
    return Escaped(text)


def sh_word(value: object) -> Escaped:
    """``sh``: a value (or a list of values) as POSIX shell words, quoted where needed.

    Raises:
        ValueError: a line break or other control character (it would end a comment, a
            Markdown code fence or the line a reader copies).
    """
    values = value if isinstance(value, list | tuple) else [value]
    return Escaped(" ".join(shlex.quote(_one_line(str(v), "shell")) for v in values))


_UNIT_WORD = re.compile(r"[A-Za-z0-9_./@:+=,-]+")


def unit_value(value: object, word: bool = False) -> Escaped:
    """``unit``: a systemd unit setting's value (``unit(word=True)`` for a path or a word
    of ``ExecStart=`` / ``Environment=``).

    ``%`` starts a specifier and is doubled; a line break or control character would start
    a new setting and a trailing backslash continue the line: refused, as are surrounding
    blanks (systemd strips them). A word also may not hold blanks, quotes, ``$`` or
    ``\\`` (command lines and assignments give them meaning).

    Raises:
        ValueError: such a value.
    """
    text = _one_line(str(value), "systemd")
    if text != text.strip() or text.endswith("\\"):
        raise ValueError(f"a systemd value cannot end in a backslash or have surrounding "
                         f"blanks: {text[:40]!r}")
    if word and not _UNIT_WORD.fullmatch(text):
        raise ValueError(f"not a plain word for a systemd setting: {text[:40]!r}")
    return Escaped(text.replace("%", "%%"))


_ENV_NAME = re.compile(r"[A-Z_][A-Z0-9_]*")
_ENV_VALUE = re.compile(r"[A-Za-z0-9_.,:/+@=-]*")


def env_assignment(pair: tuple[str, object]) -> Escaped:
    """``env``: ``NAME=VALUE`` for an env file read by systemd, docker and sh alike.

    Raises:
        ValueError: the name is not an environment variable name, or the value needs
            quoting (no quoting means the same thing to all three readers).
    """
    name, value = pair
    text = str(value)
    if not _ENV_NAME.fullmatch(name):
        raise ValueError(f"not an environment variable name: {name!r}")
    if not _ENV_VALUE.fullmatch(text):
        raise ValueError(f"{name}: value {text[:40]!r} would need quoting in an env file")
    return Escaped(f"{name}={text}")


# What Markdown (CommonMark, GitHub's) gives a meaning to in the middle of a line: emphasis,
# code, links, images, HTML and entities, tables, strikethrough, math. Backslash-escaped
# (CommonMark 2.4: any ASCII punctuation may be), so the text shows as it is.
_MD_SPECIAL = re.compile(r"([\\`*_{}\[\]<>()#+!|~&$])")


def md_text(value: object, code: bool = False) -> Escaped:
    """``md``: free text literal in Markdown prose; ``md(code=True)``: inside a
    `` `code span` `` (where backslashes are literal, so a backtick or ``|`` (a table's
    cell border) is refused instead).

    Raises:
        ValueError: a line break or control character, or surrounding blanks (Markdown
            drops them at a line's or a cell's end); in a code span, a backtick or a ``|``.
    """
    text = _one_line(str(value), "Markdown")
    if text != text.strip():
        raise ValueError(f"a Markdown value cannot have surrounding blanks: {text[:40]!r}")
    if not code:
        return Escaped(_MD_SPECIAL.sub(r"\\\1", text))
    if "`" in text or "|" in text or not text:
        raise ValueError(f"cannot be a Markdown code span: {text[:40]!r}")
    return Escaped(text)


def comment_text(value: object) -> Escaped:
    """``comment``: text in a ``#`` comment line (shell, env file, systemd unit).

    Raises:
        ValueError: a line break or control character, or a trailing backslash (systemd
            continues such a line).
    """
    text = _one_line(str(value), "comment")
    if text.endswith("\\"):
        raise ValueError(f"a comment cannot end in a backslash: {text[:40]!r}")
    return Escaped(text)


FILTERS = {"y": yaml_scalar, "wg": wg_value, "sh": sh_word, "unit": unit_value,
           "env": env_assignment, "md": md_text, "comment": comment_text}


def _require_escaped(value: object) -> object:
    """Jinja ``finalize``: every expression's output must come out of a format filter."""
    if isinstance(value, Escaped):
        return value
    if isinstance(value, jinja2.Undefined):
        str(value)  # StrictUndefined raises, naming the variable
    raise TypeError(f"a {type(value).__name__} template value skipped its format's "
                    f"escaping filter (one of {', '.join(FILTERS)})")


@functools.cache
def _environment(root: Path) -> jinja2.Environment:
    if not root.is_dir():
        raise EnvironmentMissing(f"templates directory {root} not found (set {TEMPLATES_ENV})")
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(root)),
        undefined=jinja2.StrictUndefined,
        autoescape=False,  # configs, not HTML: each format has its own filter
        keep_trailing_newline=True,
        trim_blocks=True,
        lstrip_blocks=True,
        finalize=_require_escaped,
    )
    env.filters.update(FILTERS)
    return env


def render_template(name: str, **context: object) -> str:
    """Render one template, its digest line first; a missing variable is an error."""
    try:
        body = _environment(templates_dir()).get_template(name).render(**context)
    except jinja2.TemplateNotFound:
        raise EnvironmentMissing(f"template {templates_dir() / name} not found") from None
    return stamp(body, markdown=name.endswith(".md.j2"))


def server_wireguard(fleet: Fleet, keys: FleetKeys) -> str:
    """Return the server's ``wg0.conf``: one ``[Peer]`` with a /32 per robot."""
    peers = [
        {
            "name": r.name,
            "ip": str(r.ip),
            "public_key": public_key(keys.robot(r.name).private_key, f"key of robot {r.name}"),
            "preshared_key": keys.robot(r.name).preshared_key.reveal(),
        }
        for r in fleet.robots
    ]
    return render_template(
        "wireguard/server.conf.j2",
        fleet_name=fleet.name,
        server_ip=str(fleet.server_ip),
        prefix_len=fleet.subnet.prefixlen,
        listen_port=fleet.wireguard_port,
        private_key=keys.server_private_key.reveal(),
        peers=peers,
    )


def robot_wireguard(fleet: Fleet, robot: Robot, keys: FleetKeys) -> str:
    """Return robot's ``wg0.conf``: its /32, the server as the only peer."""
    robot_keys = keys.robot(robot.name)
    return render_template(
        "wireguard/robot.conf.j2",
        fleet_name=fleet.name,
        robot_name=robot.name,
        ip=str(robot.ip),
        mtu_bytes=robot.mtu_bytes,
        private_key=robot_keys.private_key.reveal(),
        preshared_key=robot_keys.preshared_key.reveal(),
        server_public_key=public_key(keys.server_private_key, "server key"),
        endpoint=fleet.endpoint,  # None: no Endpoint line (set-endpoint adds it)
        subnet=str(fleet.subnet),
    )


def server_url(fleet: Fleet) -> str:
    """Return the WebSocket URL robots reach the server on (through the tunnel); with
    relay replicas, the first replica's."""
    return server_urls(fleet)[0]


def server_urls(fleet: Fleet) -> list[str]:
    """Every relay replica's WebSocket URL as robots reach it (one without replicas)."""
    return replica_urls(str(fleet.server_ip), fleet.server_port, fleet.relay_replicas)


def replica_urls(server_ip: str, server_port: int, count: int) -> list[str]:
    """The WebSocket URLs of *count* relay replicas through the tunnel: replica *i*
    listens on *server_port* + *i* (fleetctl.deploy.composereplicas)."""
    return [f"ws://{server_ip}:{server_port + i}/" for i in range(count)]


def client_config(fleet: Fleet, robot: Robot) -> str:
    """Return robot's ``client.yaml``: its topics (or the default set), command topics."""
    subscribe = [
        {"remote_topic": f"/{robot.name}/{c.topic}", "type": c.type, "local_topic": f"/{c.topic}"}
        for c in robot.command_topics
    ] + [
        {"remote_topic": s.remote_topic, "type": s.type, "local_topic": s.local}
        for s in robot.subscribe
    ]
    return render_template(
        "client/client.yaml.j2",
        fleet_name=fleet.name,
        robot_name=robot.name,
        server_urls=server_urls(fleet),
        bind_address=str(robot.ip),
        publish=robot.publish_topics,
        subscribe=subscribe,
        battery_topic=robot.battery_topic,
        location=robot.location,
        tf=robot.tf,
    )


def auth_map(fleet: Fleet) -> str:
    """Return ``auth.yaml`` (docs/design.md section 3)."""
    return render_template("auth/auth.yaml.j2", fleet_name=fleet.name,
                           identities=auth.identities(fleet))


def tls_paths(fleet: Fleet, fleet_dir: Path) -> tuple[str, str]:
    """Return the HTTPS certificate and key paths as ``server.yaml`` names them.

    The generated pair is named relative to ``server.yaml``'s directory (``FLEET/server``),
    so the fleet directory can move; the operator's own files by their absolute paths.
    """
    if fleet.tls is None:
        return (str(Path(CERT_RELPATH).relative_to("server")), f"../{KEY_RELPATH}")
    cert, key = fleet.tls.paths(fleet_dir.resolve())
    return str(cert), str(key)


def server_config(fleet: Fleet, fleet_dir: Path) -> str:
    """Return ``server.yaml`` (docs/design.md section 4), its HTTPS listener in ``web``."""
    cert, key = tls_paths(fleet, fleet_dir)
    return render_template("server/server.yaml.j2", fleet_name=fleet.name,
                           listen_port=fleet.server_port, https_port=fleet.https_port,
                           tls_cert=cert, tls_key=key, recording=fleet.recording,
                           msg_types=fleet.msg_types.texts)


# A robot's generated files, relative to robots/NAME/ (remove-robot tells them from an
# operator's own files by these names).
ROBOT_CLIENT_FILE = "client.yaml"
ROBOT_WIREGUARD_FILE = "wireguard/wg0.conf"
ROBOT_FILES = (ROBOT_CLIENT_FILE, ROBOT_WIREGUARD_FILE)


def fleet_artifacts(fleet: Fleet, keys: FleetKeys, fleet_dir: Path) -> list[Artifact]:
    """Return every generated file of the fleet directory (docs/design.md section 6)."""
    out = [
        Artifact("server/server.yaml", server_config(fleet, fleet_dir),
                 hint="set server_port, https_port and tls in fleet.yaml, and the fleet's "
                      "own message types in msg_types/"),
        Artifact("server/auth.yaml", auth_map(fleet),
                 hint="put rules in fleet.yaml (robots' extra_send, extra_receive and "
                      "subscribe; users)"),
        Artifact("server/wireguard/wg0.conf", server_wireguard(fleet, keys), secret=True,
                 hint="set subnet, server_ip and wireguard_port in fleet.yaml"),
    ]
    for i, robot in enumerate(fleet.robots):
        out.append(Artifact(
            f"robots/{robot.name}/{ROBOT_CLIENT_FILE}", client_config(fleet, robot),
            hint=f"put topics in fleet.yaml robots[{i}].publish / subscribe / battery_topic"))
        out.append(Artifact(
            f"robots/{robot.name}/{ROBOT_WIREGUARD_FILE}", robot_wireguard(fleet, robot, keys),
            secret=True, hint=f"set ip and mtu_bytes in fleet.yaml robots[{i}] and the "
                              "endpoint with `fleetctl set-endpoint`"))
    return out


def plan_artifacts(plan: Plan, root: Path, artifacts: list[Artifact], *,
                   force: bool = False) -> None:
    """Add writing *artifacts* under *root* to *plan* (secrets 0600 in 0700 dirs).

    Args:
        plan: the plan to extend.
        root: the directory the artifacts' paths are relative to.
        artifacts: the files.
        force: replace files edited by hand too.

    Raises:
        ConfigError: (unless *force*) a file there was edited by hand; nothing is planned.
    """
    if not force:
        for a in artifacts:
            check_overwrite(root / a.relpath, a.text, str(root / a.relpath), a.hint)
    for a in artifacts:
        plan.write(root / a.relpath, a.text, secret=a.secret)
