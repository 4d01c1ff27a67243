"""The webviz HTTP server: routes, content types, path confinement, clear 404s, and the
route lookup it shares with the relay's web listener."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetctl.webviz.config import STATIC_DIR
from fleetctl.webviz.httpserver import BackgroundWebviz, WebPage, default_server_url
from fleetctl.webviz.layouts import LayoutCache
from fleetctl.webviz.vendor import missing_vendor_libs
from fleetctl.wire.registry import TypeRegistry
from tests.webviz.conftest import webviz_server


def get(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.headers["Content-Type"], r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers["Content-Type"], e.read()


@pytest.fixture
def web(tmp_path: Path) -> Iterator[BackgroundWebviz]:
    vendor = tmp_path / "vendor"
    (vendor / "three").mkdir(parents=True)
    (vendor / "three" / "three.module.js").write_text("export const REVISION = '1';")
    (tmp_path / "secret.txt").write_text("do not serve")
    with webviz_server("ws://127.0.0.1:9/", vendor_dir=vendor) as w:
        yield w


def test_page_config_and_modules(web: BackgroundWebviz) -> None:
    status, ctype, body = get(web.url)
    assert status == 200 and ctype.startswith("text/html") and b'src="js/app.js"' in body
    status, _, body = get(web.url + "config.json")
    assert json.loads(body) == {"server_url": "ws://127.0.0.1:9/"}
    status, ctype, _ = get(web.url + "js/fb/reader.js")
    assert status == 200 and ctype.startswith("text/javascript")  # ES modules need it


def test_type_layouts(web: BackgroundWebviz) -> None:
    status, _, body = get(web.url + "types/sensor_msgs/msg/LaserScan.json")
    doc = json.loads(body)
    assert status == 200 and doc["root"] == "sensor_msgs/msg/LaserScan"
    fields = doc["tables"]["sensor_msgs/msg/LaserScan"]["fields"]
    ranges = next(f for f in fields if f["name"] == "ranges")
    assert (ranges["slot"], ranges["kind"], ranges["element"]) == (9, "scalar_vector", "float32")
    assert "builtin_interfaces/msg/Time" in doc["structs"]
    assert doc["metadata"] in doc["tables"]
    status, _, body = get(web.url + "types/nope_msgs/msg/Nope.json")
    assert status == 404 and "nope_msgs/msg/Nope" in json.loads(body)["error"]


def test_vendor_present_and_missing(web: BackgroundWebviz) -> None:
    assert get(web.url + "vendor/three/three.module.js")[0] == 200
    status, _, body = get(web.url + "vendor/leaflet/leaflet.esm.js")
    assert status == 404 and "libjs-leaflet" in json.loads(body)["error"]
    assert get(web.url + "vendor/evil/x.js")[0] == 404


@pytest.mark.parametrize(
    "path",
    [
        "../secret.txt",
        "%2e%2e/secret.txt",
        "vendor/three/../../secret.txt",
        "js/../../../../etc/passwd",
    ],
)
def test_paths_cannot_escape(web: BackgroundWebviz, path: str) -> None:
    status, _, body = get(web.url + path)
    assert status == 404 and b"do not serve" not in body and b"root:" not in body


def test_missing_vendor_libs_name_the_debian_package(tmp_path: Path) -> None:
    lines = missing_vendor_libs(tmp_path)
    assert len(lines) == 2
    assert "libjs-three" in lines[0] and "libjs-leaflet" in lines[1]
    assert missing_vendor_libs(Path("/usr/share/javascript")) == []


def test_without_server_url_config_names_port_8080_on_the_requested_host() -> None:
    with webviz_server(None) as w:
        req = urllib.request.Request(w.url + "config.json", headers={"Host": "fleet.example:8000"})
        with urllib.request.urlopen(req, timeout=10) as r:
            assert json.loads(r.read()) == {"server_url": "ws://fleet.example:8080/"}
        req.add_header("X-Forwarded-Proto", "https")  # behind a TLS proxy
        with urllib.request.urlopen(req, timeout=10) as r:
            assert json.loads(r.read()) == {"server_url": "wss://fleet.example:8080/"}
        _, _, body = get(w.url + "config.json")  # urllib sends Host: 127.0.0.1:<port>
        assert json.loads(body) == {"server_url": "ws://127.0.0.1:8080/"}


@pytest.mark.parametrize(
    ("host", "expected"),
    [
        ("robots.example", "ws://robots.example:8080/"),
        ("10.8.0.1:8000", "ws://10.8.0.1:8080/"),
        ("[fd00::1]:8000", "ws://[fd00::1]:8080/"),
        (None, "ws://127.0.0.1:8080/"),
        ("evil/\"x:1", "ws://127.0.0.1:8080/"),
    ],
)
def test_default_server_url(host: str | None, expected: str) -> None:
    assert default_server_url(host, None, "127.0.0.1") == expected


def test_one_lookup_for_every_server(tmp_path: Path) -> None:
    page = WebPage(STATIC_DIR, tmp_path, LayoutCache(TypeRegistry.default()))
    reply = page.lookup("/config.json?x=1", None)
    assert (reply.status, json.loads(reply.body)) == (200, {"server_url": None})
    reply = page.lookup("/config.json", None, (8443, 8444))  # relay replicas: failover
    assert json.loads(reply.body) == {"server_url": None, "replica_ports": [8443, 8444]}
    reply = page.lookup("/js/%61pp.js", None)
    assert reply.status == 200 and reply.content_type.startswith("text/javascript")
    reply = page.lookup("/vendor/three/three.module.js", None)
    assert reply.status == 404 and reply.error is not None and "libjs-three" in reply.error


def test_idle_connections_time_out_and_threads_are_bounded(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Silent clients cannot each hold a thread forever (issue 14, low item)."""
    import socket
    import threading

    from fleetctl.webviz import httpserver
    from tests.support import wait_for_value

    monkeypatch.setattr(httpserver._Handler, "timeout", 0.5)
    with webviz_server(None) as w:
        w.server._slots = threading.BoundedSemaphore(3)  # a small bound for the test
        w.server.max_threads = 3
        port = w.server.port
        silent = [socket.create_connection(("127.0.0.1", port)) for _ in range(3)]
        extra = socket.create_connection(("127.0.0.1", port))
        extra.settimeout(5)
        assert extra.recv(1) == b""  # refused at once: no fourth thread
        assert wait_for_value(lambda: w.server.refused == 1, 5)
        for s in silent:  # each silent connection is dropped after the timeout
            s.settimeout(5)
            assert s.recv(1) == b""
        assert get(w.url)[0] == 200  # the slots came back
        for s in [*silent, extra]:
            s.close()
