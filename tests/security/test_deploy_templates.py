"""Every template, rendered with a hostile value in every field (issue 14).

For each template under ``templates/`` and each value it takes, the value is replaced by
each of :data:`HOSTILE` in turn. Either its format's filter refuses it (a ``ValueError``
naming the problem: no file is written), or the output parses to exactly the intended
structure: the structure of the same template rendered with a harmless marker in that
field, the marker replaced by the hostile value (WireGuard: the same sections and keys
as wg-quick reads them; YAML: ``yaml.safe_load`` equal; shell: ``bash -n`` and the value
comes out of the shell as it went in; systemd: the same sections and settings; env file:
the same assignments; Markdown: the same blocks, table cells, code spans and inline
markup, and its shell blocks word for word). And never a new line.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from fleetctl.deploy.render import Escaped, render_template, templates_dir

MARKER = "Zmark0"  # accepted by every filter, found nowhere else in a template
HOSTILE = (
    "a\nb", "a\rb", "a\u2028b", "a\x85b", "a\x00b", "q\"uo'te", "$(touch /tmp/PWNED)",
    "`id`", "a # b", "[Peer]", "x\n[Interface]\nPostUp = touch /tmp/PWNED #", "100%i %%",
    "x" * 5000, "caf\u00e9 \U0001f916 \u4e2d", "back\\", " padded ", "*_<b>&amp;|~$x$",
)

# The values every template takes (bundle.py and render.py pass these), all harmless.
CONTEXTS: dict[str, dict[str, Any]] = {
    "wireguard/server.conf.j2": {
        "fleet_name": "campus", "server_ip": "10.8.0.1", "prefix_len": 24,
        "listen_port": 51820, "private_key": "cHJpdmF0ZQ==",
        "peers": [{"name": "husky1", "ip": "10.8.0.2", "public_key": "cHVibGlj",
                   "preshared_key": "cHNr"}],
    },
    "wireguard/robot.conf.j2": {
        "fleet_name": "campus", "robot_name": "husky1", "ip": "10.8.0.2", "mtu_bytes": 1280,
        "private_key": "cHJpdmF0ZQ==", "preshared_key": "cHNr", "server_public_key": "cHVi",
        "endpoint": "vpn.example.com:51820", "subnet": "10.8.0.0/24",
    },
    "auth/auth.yaml.j2": {
        "fleet_name": "campus",
        "identities": [{"name": "husky1", "kind": "ip", "value": "10.8.0.2",
                        "rules": [{"topic": "/husky1/.*", "op": "send"}]},
                       {"name": "a@example.com", "kind": "token_sha256", "value": "ab" * 32,
                        "rules": [{"topic": ".*", "op": "both"}]}],
    },
    "client/client.yaml.j2": {
        "fleet_name": "campus", "robot_name": "husky1",
        # Two relay replicas: the list form, each URL a value of its own.
        "server_urls": ["ws://10.8.0.1:8080/", "ws://10.8.0.1:8081/"],
        "bind_address": "10.8.0.2", "battery_topic": "/battery", "location": "yard 3",
        "publish": [{"topic": "/odom", "type": "nav_msgs/msg/Odometry", "priority": 4.0,
                     "rate_limit_hz": 10.0, "no_drop": False, "compression": "none",
                     "video": None, "viewer_cloud": None},
                    {"topic": "/camera/image_raw", "type": "sensor_msgs/msg/Image",
                     "priority": 1.0, "rate_limit_hz": None, "no_drop": False,
                     "compression": "none",
                     "video": {"codec": "h264", "max_bitrate_kbps": 1000,
                               "min_bitrate_kbps": 100, "keyframe_interval_s": 2.0},
                     "viewer_cloud": None},
                    {"topic": "/points", "type": "sensor_msgs/msg/PointCloud2",
                     "priority": 1.0, "rate_limit_hz": 5.0, "no_drop": False,
                     "compression": "deflate", "video": None,
                     "viewer_cloud": {"resolution_m": 0.01}}],
        "subscribe": [{"remote_topic": "/husky1/goal_pose", "type": "geometry_msgs/msg/Pose",
                       "local_topic": "/goal_pose"}],
        "tf": {"translation_delta_m": 0.01, "rotation_delta_rad": 0.01, "max_rate_hz": 10.0},
    },
    "server/server.yaml.j2": {
        "fleet_name": "campus", "listen_port": 8080, "https_port": 8443,
        "tls_cert": "tls/cert.pem", "tls_key": "../keys/tls.key",
        # fleet.yaml's recording section (a FleetRecording; its fields by name).
        "recording": {"topics": ["/.*/map", "/husky1/.*"], "max_file_bytes": 268435456,
                      "max_total_bytes": 10737418240, "max_age_s": 604800},
        # The fleet's own message types (FLEET/msg_types): (pkg/msg/Name, .msg text).
        "msg_types": [["my_robot_msgs/msg/Status", "uint8 level\nstring text  # why\n"]],
    },
    "robot/fleetctl-client.service.j2": {
        "description": "fleetctl robot client of husky1 (fleet campus)", "interface": "fleet0",
        "env_file": "/etc/fleetctl/fleetctl.env", "wrapper": "/usr/local/bin/fleetctl-client",
        "state_dir": "/var/lib/fleetctl",
    },
    "robot/fleetctl-client.sh.j2": {
        "robot_name": "husky1", "ros_setup": "/opt/ros/jazzy/setup.bash",
        "venv": "/opt/fleetctl", "config": "/etc/fleetctl/client.yaml",
    },
    "robot/fleetctl.env.j2": {
        "robot_name": "husky1", "fleet_name": "campus", "fastdds": True,
        "environment": [("ROS_DOMAIN_ID", 0), ("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")],
    },
    "client/README.md.j2": {
        "fleet_name": "campus", "robot_name": "husky1", "ip": "10.8.0.2",
        "endpoint": "vpn.example.com:51820", "mtu_bytes": 1280,
        "server_url": "ws://10.8.0.1:8080/", "server_ip": "10.8.0.1", "ros_domain_id": 0,
        # Two relay replicas: the README names both (server_urls is rendered).
        "server_urls": "ws://10.8.0.1:8080/, ws://10.8.0.1:8081/",
        "rmw": "rmw_cyclonedds_cpp", "rmw_is_fastdds": False, "default_rmw": "rmw_fastrtps_cpp",
        "iface": "fleet0", "wheel": "./fleetctl-0.1.0-py3-none-any.whl",
        "wheel_name": "fleetctl-0.1.0-py3-none-any.whl", "venv": "/opt/fleetctl",
        "etc": "/etc/fleetctl", "ros_setup": "/opt/ros/jazzy/setup.bash",
        "wrapper": "/usr/local/bin/fleetctl-client", "unit": "fleetctl-client.service",
        "image": "fleetctl/client:0.1.0", "image_archive": "fleetctl-client-0.1.0.tar.gz",
        "docker_run": Escaped("docker run -d fleetctl/client:0.1.0"),  # quoted in bundle.py
        "ros_wheels": ["ros-jazzy-rclpy[fastrtps]>=7,<8", "pillow>=10,<14"],
        "files": {"wg": "wg0.conf", "client": "client.yaml", "env": "fleetctl.env",
                  "wrapper": "fleetctl-client", "compose": "compose.yaml"},
    },
}

Path_ = tuple[str | int, ...]


def _leaves(value: Any, path: Path_ = ()) -> Iterator[Path_]:
    """Paths of every value a template prints (bools and None only steer ``if``s)."""
    if value is None or isinstance(value, Escaped | bool):
        return
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _leaves(item, (*path, key))
    elif isinstance(value, list | tuple):
        for i, item in enumerate(value):
            yield from _leaves(item, (*path, i))
    else:
        yield path


def _with(value: Any, path: Path_, new: str) -> Any:
    if not path:
        return new
    head, rest = path[0], path[1:]
    if isinstance(value, dict):
        return {k: _with(v, rest, new) if k == head else v for k, v in value.items()}
    items = [_with(v, rest, new) if i == head else v for i, v in enumerate(value)]
    return tuple(items) if isinstance(value, tuple) else items


def _marker(path: Path_) -> str:
    """The harmless stand-in of a field (a YAML key or an env name is a word of its own)."""
    if path[-1] == "kind":
        return MARKER.lower()
    if path[0] == "environment" and path[-1] == 0:
        return MARKER.upper()
    return MARKER


def _render(name: str, context: dict[str, Any]) -> str | None:
    """The rendered text without its digest line, or ``None`` when a filter refuses a
    value."""
    try:
        return render_template(name, **context).partition("\n")[2]
    except ValueError:
        return None


def _subst(value: Any, marker: str, new: str) -> Any:
    """*value* (parsed output) with *marker* replaced by *new* in every string."""
    if isinstance(value, str):
        return value.replace(marker, new)
    if isinstance(value, dict):
        return {_subst(k, marker, new): _subst(v, marker, new) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(_subst(v, marker, new) for v in value)
    return value


# --- parsers: what each format's reader makes of a file --------------------------------


def parse_wireguard(text: str) -> list[tuple[str, str, str]]:
    """(section, key, value) as wg-quick's parse_options reads them: cut at '#', split
    at the first '=', strip blanks."""
    out, section = [], ""
    for line in text.splitlines():
        stripped = line.split("#", 1)[0]
        key, _, value = stripped.partition("=")
        key, value = key.strip(), value.strip()
        if key.startswith("["):
            section = key
        elif key:
            out.append((section, key, value))
    return out


def parse_yaml(text: str) -> Any:
    return yaml.safe_load(text)


def parse_unit(text: str) -> list[tuple[str, str, str]]:
    """(section, key, value) as systemd reads them (``%%`` is a literal ``%``)."""
    out, section = [], ""
    for line in text.splitlines():
        if not line.strip() or line.startswith(("#", ";")):
            continue
        assert not line.endswith("\\"), f"a continued line: {line!r}"
        if line.startswith("["):
            section = line
            continue
        key, sep, value = line.partition("=")
        assert sep, f"not a setting: {line!r}"
        out.append((section, key.strip(), value.strip().replace("%%", "%")))
    return out


def parse_env(text: str) -> list[tuple[str, str]]:
    out = []
    for line in text.splitlines():
        if line and not line.startswith("#"):
            key, sep, value = line.partition("=")
            assert sep and re.fullmatch(r"[A-Z_][A-Z0-9_]*", key), line
            out.append((key, value))
    return out


def parse_shell(text: str) -> tuple[str, str]:
    """What the wrapper script does: ``bash -n``, then run with ``exec`` replaced by a
    function that prints its arguments (so the values come out as the shell sees them)."""
    with tempfile.NamedTemporaryFile("w", suffix=".sh", delete=False) as f:
        f.write(text)
    try:
        subprocess.run(["bash", "-n", f.name], check=True, capture_output=True)
        res = subprocess.run(
            ["bash", "-c", 'exec() { printf "<%s>" "$@"; }; source "$0"', f.name],
            capture_output=True, text=True, check=True,
            env={"PATH": os.environ["PATH"]})
    finally:
        os.unlink(f.name)
    return res.stdout, res.stderr


_MD_ESCAPABLE = "!\"#$%&'()*+,-./:;<=>?@[\\]^_`{|}~"


def _inline(text: str) -> list[tuple[str, str]]:
    """Markdown inline tokens: ('code', span), ('mark', a special character with its
    meaning), ('text', literal text, backslash escapes resolved)."""
    tokens: list[tuple[str, str]] = []
    i = 0
    while i < len(text):
        c = text[i]
        if c == "\\" and i + 1 < len(text) and text[i + 1] in _MD_ESCAPABLE:
            tokens.append(("text", text[i + 1]))
            i += 2
        elif c == "`":
            run = len(text[i:]) - len(text[i:].lstrip("`"))
            end = text.find("`" * run, i + run)
            assert end >= 0, f"an unclosed code span: {text!r}"
            tokens.append(("code", text[i + run:end]))
            i = end + run
        elif c in "*_[]<>!&|~$":
            tokens.append(("mark", c))
            i += 1
        else:
            tokens.append(("text", c))
            i += 1
    merged: list[tuple[str, str]] = []
    for kind, part in tokens:  # adjacent text characters become one token
        if merged and kind == "text" and merged[-1][0] == "text":
            merged[-1] = ("text", merged[-1][1] + part)
        else:
            merged.append((kind, part))
    return merged


def parse_markdown(text: str) -> list[Any]:
    """Blocks: headings, table rows (cells), fenced code (shell words per line, after
    ``bash -n``), HTML comments, paragraphs' inline tokens."""
    blocks: list[Any] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("```"):
            end = lines.index("```", i + 1)
            body = "\n".join(lines[i + 1:end])
            if line == "```sh":
                subprocess.run(["bash", "-n", "-c", body], check=True)
            blocks.append(("fence", line, [shlex.split(ln) for ln in lines[i + 1:end]]))
            i = end + 1
            continue
        if line.startswith("|"):
            cells = re.split(r"(?<!\\)\|", line)
            blocks.append(("row", [_inline(c.strip()) for c in cells]))
        elif line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            blocks.append(("heading", level, _inline(line[level:].strip())))
        elif line.startswith("<!--"):
            blocks.append(("html", line))
        else:
            blocks.append(("para", _inline(line)))
        i += 1
    return blocks


PARSERS: dict[str, tuple[Callable[[str], Any], bool]] = {
    # suffix: (parser, whether the format can hold any string: then nothing is refused)
    ".conf.j2": (parse_wireguard, False),
    ".yaml.j2": (parse_yaml, True),
    ".service.j2": (parse_unit, False),
    ".sh.j2": (parse_shell, False),
    ".env.j2": (parse_env, False),
    ".md.j2": (parse_markdown, False),
}


def _parser(name: str) -> tuple[Callable[[str], Any], bool]:
    return next(v for suffix, v in PARSERS.items() if name.endswith(suffix))


def test_every_template_is_covered() -> None:
    root = templates_dir()
    names = {str(p.relative_to(root)) for p in root.rglob("*.j2")}
    assert names == set(CONTEXTS), "give every template a context here"
    for name in names:
        _parser(name)


def _cases() -> Iterator[Any]:
    for name, context in CONTEXTS.items():
        for path in _leaves(context):
            yield pytest.param(name, path, id=f"{name}:{'.'.join(map(str, path))}")


@pytest.mark.parametrize(("name", "path"), list(_cases()))
def test_hostile_value_keeps_the_structure(name: str, path: Path_) -> None:
    parse, holds_anything = _parser(name)
    marker = _marker(path)
    base_text = _render(name, _with(CONTEXTS[name], path, marker))
    assert base_text is not None and marker in base_text
    base = parse(base_text)
    for hostile in HOSTILE:
        text = _render(name, _with(CONTEXTS[name], path, hostile))
        if text is None:
            # A YAML mapping key (auth.yaml's identity kind) is a plain word, never data.
            assert not holds_anything or path[-1] == "kind", (
                f"{name} refused {hostile[:30]!r} in {path}")
            continue
        assert len(text.splitlines()) == len(base_text.splitlines()), (
            f"{hostile[:30]!r} in {path} added a line to {name}")
        assert parse(text) == _subst(base, marker, hostile), (
            f"{hostile[:30]!r} in {path} of {name}")


def test_a_refusal_says_why() -> None:
    context = _with(CONTEXTS["wireguard/robot.conf.j2"], ("fleet_name",),
                    "x\n[Interface]\nPostUp = touch /tmp/PWNED #")
    with pytest.raises(ValueError, match="WireGuard config value must be one printable line"):
        render_template("wireguard/robot.conf.j2", **context)


def test_a_value_without_its_filter_is_an_error(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "bad.conf.j2").write_text("Name = {{ robot_name }}\n")
    monkeypatch.setenv("FLEETCTL_TEMPLATES", str(tmp_path))
    with pytest.raises(TypeError, match="skipped its format's escaping filter"):
        render_template("bad.conf.j2", robot_name="x")
