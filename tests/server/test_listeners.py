"""The relay's listeners: several addresses, the HTTPS web listener (page + WebSocket on one
origin), its config validation, and what websockets' request log keeps."""

from __future__ import annotations

import asyncio
import json
import logging
import ssl
from collections.abc import Callable
from pathlib import Path

import pytest
from websockets.asyncio.client import connect

from fleetctl.errors import ConfigError
from fleetctl.server.app import ListenError, RelayServer
from fleetctl.server.config import ServerLimits, WebConfig, load_server_config
from tests.server.certs import self_signed
from tests.server.conftest import ALICE_TOKEN, client, next_binary, next_json, subscribe
from tests.server.test_app import closed_code, http_get
from tests.support import decode_text, string_frame


def client_tls() -> ssl.SSLContext:
    context = ssl.create_default_context()
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE  # the test's self-signed certificate
    return context


async def https_get(port: int, path: str) -> tuple[int, dict[str, str], bytes]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port, ssl=client_tls())
    writer.write(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    data = await asyncio.wait_for(reader.read(), 5)
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    headers = dict(line.split(": ", 1) for line in lines[1:])
    return int(lines[0].split()[1]), {k.lower(): v for k, v in headers.items()}, body


@pytest.fixture
def web_config(tmp_path: Path) -> WebConfig:
    cert, key = self_signed(tmp_path / "tls")
    vendor = tmp_path / "vendor"
    (vendor / "three").mkdir(parents=True)
    (vendor / "three" / "three.module.js").write_text("export const REVISION = '1';")
    return WebConfig(tls_cert=cert, tls_key=key, listen_host="127.0.0.1", listen_port=0,
                     vendor_dir=vendor)


async def test_web_listener_serves_page_and_relay_on_one_origin(
    make_server: Callable[..., RelayServer], web_config: WebConfig
) -> None:
    async with make_server(web=web_config, limits=ServerLimits(auth_timeout_s=0.3)) as srv:
        port = srv.web_port
        assert srv.web_url == f"https://127.0.0.1:{port}/"
        status, headers, body = await https_get(port, "/")
        assert status == 200 and headers["content-type"].startswith("text/html")
        assert b'src="js/app.js"' in body and headers["cache-control"] == "no-cache"
        assert json.loads((await https_get(port, "/config.json"))[2]) == {"server_url": None}
        status, headers, body = await https_get(port, "/js/app.js")
        assert status == 200 and headers["content-type"].startswith("text/javascript")
        status, _, body = await https_get(port, "/types/sensor_msgs/msg/LaserScan.json")
        assert status == 200 and json.loads(body)["root"] == "sensor_msgs/msg/LaserScan"
        assert (await https_get(port, "/vendor/three/three.module.js"))[0] == 200
        assert (await https_get(port, "/healthz"))[:3:2] == (200, b"ok\n")
        assert (await https_get(port, "/../../etc/passwd"))[0] == 404
        assert (await https_get(port, "/metrics"))[0] == 404  # stays on the relay port

        url = f"wss://127.0.0.1:{port}/"
        async with connect(url, ssl=client_tls()) as browser, \
                client(srv, source="127.0.0.2") as robot:
            await browser.send(json.dumps({"token": ALICE_TOKEN}))
            assert (await next_json(browser, "welcome"))["identities"] == ["alice"]
            assert (await subscribe(browser, "/husky1/.*"))["type"] == "subscribed"
            await robot.send(string_frame("/husky1/chat", "to the page"))
            assert decode_text(await next_binary(browser)) == "to the page"
        # Address identities do not apply on the web listener: 127.0.0.2 is husky1 on the
        # relay port, nobody here until it sends a token.
        async with connect(url, ssl=client_tls(), local_addr=("127.0.0.2", 0)) as ws:
            assert await closed_code(ws) == 4403
        async with connect(url, ssl=client_tls(),
                           additional_headers={"Authorization": f"Bearer {ALICE_TOKEN}"}) as ws:
            assert (await next_json(ws, "welcome"))["identities"] == ["alice"]


async def test_several_listen_addresses(
    make_server: Callable[..., RelayServer], web_config: WebConfig
) -> None:
    web = WebConfig(**{**web_config.__dict__, "listen_host": ("127.0.0.1", "127.0.0.2")})
    async with make_server(listen_host=("127.0.0.1", "127.0.0.2"), web=web) as srv:
        # Port 0 picks a free port per address: every socket answers.
        assert {h for h, _ in srv.addresses} == {"127.0.0.1", "127.0.0.2"}
        assert {h for h, _ in srv.web_addresses} == {"127.0.0.1", "127.0.0.2"}
        for host, port in srv.addresses:
            reader, writer = await asyncio.open_connection(host, port)
            writer.write(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            assert (await asyncio.wait_for(reader.read(), 5)).endswith(b"ok\n")
            writer.close()
        for host, port in srv.web_addresses:
            reader, writer = await asyncio.open_connection(host, port, ssl=client_tls())
            writer.write(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            assert (await asyncio.wait_for(reader.read(), 5)).endswith(b"ok\n")
            writer.close()


async def test_busy_port_names_the_field(
    make_server: Callable[..., RelayServer], web_config: WebConfig
) -> None:
    async with make_server() as first:
        web = WebConfig(**{**web_config.__dict__, "listen_port": first.port})
        second = make_server(web=web)
        with pytest.raises(ListenError, match=f"'web.listen_port'.*127.0.0.1:{first.port}"):
            await second.start()


async def test_an_address_this_machine_lacks_names_the_host_field(
    make_server: Callable[..., RelayServer],
) -> None:
    """192.0.2.1 (TEST-NET-1) is on no interface here: the address is at fault, not the
    port, and the message says listen_host."""
    with pytest.raises(ListenError, match=r"field 'listen_host': cannot listen on 192\.0\.2\.1"):
        await make_server(listen_host="192.0.2.1").start()


async def test_successful_http_answers_are_not_logged_as_rejections(
    make_server: Callable[..., RelayServer], web_config: WebConfig,
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO)
    async with make_server(web=web_config) as srv:
        assert (await http_get(srv.port, "/healthz"))[0] == 200
        assert (await http_get(srv.port, "/metrics"))[0] == 200
        assert (await https_get(srv.web_port, "/"))[0] == 200
        assert (await http_get(srv.port, "/robots", {"Authorization": "Bearer bad"}))[0] == 401
        assert (await https_get(srv.web_port, "/nope.js"))[0] == 404
    rejected = [r.getMessage() for r in caplog.records if "connection rejected" in r.getMessage()]
    assert rejected == ["connection rejected (401 Unauthorized)",
                        "connection rejected (404 Not Found)"]


# -- config ------------------------------------------------------------------------------


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "server.yaml"
    path.write_text(text)
    return path


def test_web_section_paths_are_relative_to_the_file(tmp_path: Path) -> None:
    self_signed(tmp_path / "tls")
    cfg = load_server_config(write(tmp_path, """
auth_map: auth.yaml
listen_host: [10.8.0.1, 127.0.0.1]
web:
  listen_host: 127.0.0.1
  tls_cert: tls/cert.pem
  tls_key: tls/../tls/key.pem
"""))
    assert cfg.listen_host == ("10.8.0.1", "127.0.0.1")
    assert cfg.web is not None and cfg.web.listen_port == 8443
    assert cfg.web.tls_cert == tmp_path / "tls" / "cert.pem"
    assert cfg.web.listen_host == "127.0.0.1"
    assert cfg.web.vendor_dir == Path("/usr/share/javascript")
    assert cfg.web.replica_ports == ()
    assert load_server_config(write(tmp_path, "auth_map: a.yaml\n")).web is None
    replicas = load_server_config(write(tmp_path, "auth_map: a.yaml\nweb: {tls_cert: "
                                        "tls/cert.pem, tls_key: tls/key.pem, "
                                        "replica_ports: [8443, 8444]}\n"))
    assert replicas.web is not None and replicas.web.replica_ports == (8443, 8444)


@pytest.mark.parametrize(
    ("web", "field"),
    [
        ("{tls_key: tls/key.pem}", "web.tls_cert"),
        ("{tls_cert: tls/cert.pem}", "web.tls_key"),
        ("{tls_cert: tls/nope.pem, tls_key: tls/key.pem}", "web.tls_cert"),
        ("{tls_cert: tls/cert.pem, tls_key: tls/key.pem, listen_port: 99999}",
         "web.listen_port"),
        ("{tls_cert: tls/cert.pem, tls_key: tls/key.pem, listen_host: []}", "web.listen_host"),
        ("{tls_cert: tls/cert.pem, tls_key: tls/key.pem, bogus: 1}", "web.bogus"),
        ("{tls_cert: tls/cert.pem, tls_key: tls/key.pem, replica_ports: 8443}",
         "web.replica_ports"),
        ("{tls_cert: tls/cert.pem, tls_key: tls/key.pem, replica_ports: [8443, 0]}",
         "web.replica_ports[1]"),
        ("{tls_cert: tls/cert.pem, tls_key: tls/key.pem, replica_ports: [8443, '8444']}",
         "web.replica_ports[1]"),
        ("{tls_cert: tls/cert.pem, tls_key: tls/key.pem, replica_ports: [8443, 8443]}",
         "web.replica_ports"),
        ("[1]", "'web'"),
        ("{tls_cert: tls/key.pem, tls_key: tls/cert.pem}", "web.tls_cert"),  # swapped
        ("{tls_cert: tls/junk.pem, tls_key: tls/key.pem}", "web.tls_cert"),
    ],
)
def test_bad_web_section_names_file_and_field(tmp_path: Path, web: str, field: str) -> None:
    self_signed(tmp_path / "tls")
    (tmp_path / "tls" / "junk.pem").write_text("not a certificate")
    path = write(tmp_path, f"auth_map: a.yaml\nweb: {web}\n")
    with pytest.raises(ConfigError) as err:
        load_server_config(path)
    assert str(path) in str(err.value) and field in str(err.value)
    assert "Traceback" not in str(err.value)


def test_unreadable_key_is_a_config_error(tmp_path: Path) -> None:
    import os

    _, key = self_signed(tmp_path / "tls")
    key.chmod(0)
    if os.access(key, os.R_OK):
        pytest.skip("running as root: file modes do not stop reading")
    path = write(tmp_path, "auth_map: a.yaml\nweb: {tls_cert: tls/cert.pem, tls_key: tls/key.pem}")
    with pytest.raises(ConfigError, match=r"web\.tls_key.*cannot read"):
        load_server_config(path)


@pytest.mark.parametrize("value", ["[]", "[1, 2]", "''", "{a: 1}"])
def test_bad_listen_host(tmp_path: Path, value: str) -> None:
    path = write(tmp_path, f"auth_map: a.yaml\nlisten_host: {value}\n")
    with pytest.raises(ConfigError, match="listen_host"):
        load_server_config(path)
