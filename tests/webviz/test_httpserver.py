"""The webviz HTTP server: routes, content types, path confinement, clear 404s."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetctl.webviz.httpserver import BackgroundWebviz
from fleetctl.webviz.vendor import missing_vendor_libs
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
