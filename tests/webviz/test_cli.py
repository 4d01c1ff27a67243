"""``fleetctl webviz`` as a process: serves, says where, stops cleanly on SIGTERM."""

from __future__ import annotations

import contextlib
import json
import re
import signal
import subprocess
import sys
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

from fleetctl.cli.main import main
from fleetctl.deploy.msgtypes import load_msg_types
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.schema import describe

START_TIMEOUT_S = 30


@contextlib.contextmanager
def webviz_process(*args: str) -> Iterator[tuple[str, list[str]]]:
    """``fleetctl webviz --port 0 ARGS`` as a user runs it; yields its URL and the lines it
    wrote up to the one saying so, and stops it with SIGTERM (exit 0 expected)."""
    cmd = [sys.executable, "-m", "fleetctl.cli.main", "webviz", "--port", "0", *args]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        lines = []
        for _ in range(20):  # warnings (e.g. a missing vendored library) may come first
            lines.append(proc.stderr.readline())  # blocks until a line or EOF (exit)
            m = re.search(r"serving (http://\S+)", lines[-1])
            if m or not lines[-1]:
                break
        assert m, "".join(lines)
        yield m.group(1), lines
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=START_TIMEOUT_S) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as err:
        return err.code, err.read()


def test_serves_until_sigterm() -> None:
    with webviz_process("--server-url", "ws://127.0.0.1:9/") as (url, _):
        assert get(url + "config.json") == (200, b'{"server_url": "ws://127.0.0.1:9/"}')


STATUS_MSG = "string mission\nfloat32 progress\nmy_robot_msgs/Arm[] arms\n"
ARM_MSG = "string name\nfloat64[6] joints\n"


def write_fleet_types(fleet: Path, files: dict[str, str]) -> Path:
    """FLEET/msg_types/<relpath> for each file, as an operator copies a package's msg/."""
    for relpath, text in files.items():
        path = fleet / "msg_types" / relpath
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return fleet


def test_serves_the_layouts_of_the_fleets_own_types(tmp_path: Path) -> None:
    # fleetctl render puts them in server.yaml, so the relay's own page knew them; a page
    # served by fleetctl webviz answered 404 and showed nothing for a robot's own type.
    fleet = write_fleet_types(tmp_path, {"my_robot_msgs/msg/Status.msg": STATUS_MSG,
                                         "my_robot_msgs/msg/Arm.msg": ARM_MSG})
    status = "types/my_robot_msgs/msg/Status.json"
    with webviz_process() as (url, _):
        code, body = get(url + status)
        assert code == 404 and b"my_robot_msgs/msg/Status" in body
    with webviz_process("--fleet", str(fleet)) as (url, lines):
        code, body = get(url + status)
        assert code == 200, body
        assert "the fleet's own message types too: my_robot_msgs/msg/Arm" in "".join(lines)
        doc = json.loads(body)
        assert doc == describe(TypeRegistry.default_with(load_msg_types(fleet).texts),
                               "my_robot_msgs/msg/Status")
        assert "mission" in body.decode() and "progress" in body.decode()
        assert get(url + "types/sensor_msgs/msg/LaserScan.json")[0] == 200  # still served


def test_bad_fleet_types_are_one_line_naming_the_file(tmp_path: Path, capsys: object) -> None:
    missing = tmp_path / "nowhere"
    assert main(["webviz", "--fleet", str(missing)]) == 3
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert err == (f"fleetctl: error: --fleet {str(missing)!r}: not a directory (a fleet "
                   "directory, whose msg_types/PKG/msg/NAME.msg the page decodes too)\n")
    bad = write_fleet_types(tmp_path / "bad", {
        "my_robot_msgs/msg/Status.msg": "string mission\n!!! not a field\n"})
    assert main(["webviz", "--fleet", str(bad)]) == 3
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    where = bad / "msg_types/my_robot_msgs/msg/Status.msg"
    assert err.startswith(f"fleetctl: error: {where}:2: cannot parse"), err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    undefined = write_fleet_types(tmp_path / "undefined", {
        "my_robot_msgs/msg/Status.msg": "my_robot_msgs/Arm arm\n"})
    assert main(["webviz", "--fleet", str(undefined)]) == 3
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert err.startswith(f"fleetctl: error: {undefined}/msg_types/my_robot_msgs/msg/"
                          "Status.msg:1: field 'arm'"), err
    assert len(err.strip().splitlines()) == 1


def test_a_fleet_without_types_of_its_own_is_said(tmp_path: Path) -> None:
    with webviz_process("--fleet", str(tmp_path)) as (url, lines):
        assert f"{tmp_path} has no msg_types/PKG/msg/NAME.msg" in "".join(lines)
        assert get(url + "types/sensor_msgs/msg/LaserScan.json")[0] == 200


def test_bad_server_url_is_a_clear_error(capsys: object) -> None:
    assert main(["webviz", "--server-url", "http://host:8080/"]) == 3
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert "--server-url" in err and "ws://" in err


def test_malformed_server_url_is_a_clear_error(capsys: object) -> None:
    for url in ("ws://[::1/", "ws://host:99999/", "ws://host:port/"):
        assert main(["webviz", "--server-url", url]) == 3
        err = capsys.readouterr().err  # type: ignore[attr-defined]
        assert err.startswith(f"fleetctl: error: --server-url {url!r}: expected ws://")
        assert "Traceback" not in err


def test_port_in_use_is_a_clear_error(capsys: object) -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["webviz", "--port", str(port)]) == 5
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert f"cannot listen on 127.0.0.1:{port}" in err


def test_bad_host_is_a_config_error_naming_the_option(capsys: object) -> None:
    """It was exit 5 ('cannot listen on not a host:8000'), as if the machine lacked
    something, and did not name --host."""
    for host in ("not a host", "", "1.2.3.999", "010.0.0.1", "-x.example", "a..b",
                 "x" * 300, "h\u00e9.example"):
        assert main(["webviz", "--host", host]) == 3
        err = capsys.readouterr().err  # type: ignore[attr-defined]
        assert err.startswith(f"fleetctl: error: --host {host[:80]!r}: not an IP address "
                              "or a host name"), err
        assert len(err.strip().splitlines()) == 1


def test_host_that_does_not_resolve_is_a_config_error(capsys: object,
                                                      monkeypatch: object) -> None:
    import socket

    def no_such_name(*_args: object, **_kwargs: object) -> list[object]:
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(socket, "getaddrinfo", no_such_name)  # type: ignore[attr-defined]
    assert main(["webviz", "--host", "nosuch.invalid"]) == 3
    err = capsys.readouterr().err  # type: ignore[attr-defined]
    assert err == ("fleetctl: error: --host 'nosuch.invalid': cannot resolve it: "
                   "Name or service not known\n")
