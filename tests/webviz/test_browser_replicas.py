"""The page fails over between relay replicas (issue 15), in Chromium, with two real
replicas on a real nats-server and a real WebSocket robot.

The page is opened on replica A; the robot is on replica B (its topics cross NATS). A
stops: the page reconnects to B on its own (same host name, B's port from
``web.replica_ports``), keeps its sign-in, and shows the robot's live scan again; a type
layout whose fetch from A failed as A stopped is loaded again, from B.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import load_auth_map
from fleetctl.server.cluster.config import ClusterConfig
from fleetctl.server.config import ServerConfig, WebConfig
from fleetctl.wire.codec import Codec
from fleetctl.wire.registry import TypeRegistry
from tests.server.certs import self_signed
from tests.server.cluster.natsproc import NatsServer, free_port, nats_binary
from tests.webviz.fleet import OPERATOR_TOKEN, WsRobot, write_auth_map
from tests.webviz.test_browser import sign_in, wait_js, watch_errors

pytest.importorskip("nats")
pytestmark = [pytest.mark.browser, pytest.mark.slow,
              pytest.mark.skipif(nats_binary() is None, reason="no nats-server binary")]


@contextlib.asynccontextmanager
async def two_replicas(tmp_path: Path) -> AsyncIterator[tuple[RelayServer, RelayServer]]:
    nats = NatsServer("solo", tmp_path)
    nats.start()
    cert, key = self_signed(tmp_path / "tls")
    auth_path = write_auth_map(tmp_path / "auth.yaml", {"r1": "127.0.0.2"})
    ports = (free_port(), free_port())

    def replica(name: str, port: int) -> RelayServer:
        web = WebConfig(tls_cert=cert, tls_key=key, listen_host="127.0.0.1",
                        listen_port=port, replica_ports=ports)
        config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=auth_path,
                              database=None, web=web,
                              cluster=ClusterConfig(name=name, nats_urls=(nats.url,)))
        return RelayServer(config, load_auth_map(auth_path))

    a, b = replica("relay-a", ports[0]), replica("relay-b", ports[1])
    try:
        await a.start()
        await b.start()
        yield a, b
    finally:
        await a.stop()
        await b.stop()
        nats.stop()


async def test_the_page_fails_over_to_another_replica(tmp_path: Path, browser: Any) -> None:
    async with two_replicas(tmp_path) as (a, b):
        robot = WsRobot("r1", "127.0.0.2", b.url, Codec(TypeRegistry.default()))
        await robot.start()
        context = await browser.new_context(ignore_https_errors=True)
        try:
            page = await context.new_page()
            problems = watch_errors(page)
            failed: list[str] = []
            page.on("requestfailed", lambda r: failed.append(r.url))
            assert a.web_url is not None and b.web_port is not None
            await sign_in(page, a.web_url, OPERATOR_TOKEN)
            row = page.locator('#robots tr[data-robot="r1"]')
            await row.locator("td.state", has_text="online").wait_for(timeout=15_000)
            await page.click('#robots a[href="#/robot/r1"]')
            await wait_js(page, "Number(document.querySelector('#scan-canvas').dataset.beams"
                                " || 0) === 360")
            a_origin = a.web_url
            await a.stop()  # replica A goes away under the page
            await wait_js(page, "window.fleetviz.conn.url === "
                                f"'wss://127.0.0.1:{b.web_port}/' && "
                                "document.querySelector('#conn-state').textContent === 'open'")
            # Live data again, through B: the scan panel is redrawn from new frames.
            await page.evaluate("document.querySelector('#scan-canvas').dataset.beams = '0'")
            await wait_js(page, "Number(document.querySelector('#scan-canvas').dataset.beams"
                                " || 0) === 360")
            assert await page.is_hidden("#signin")  # still signed in
            # A layout fetch in flight to A as it stopped fails (its frame had come from
            # A): never remembered, it is asked again from the replica the page is on.
            on_a = [u for u in failed if u.startswith(a_origin)]
            assert failed == on_a, failed
            for url in on_a:
                type_name = url.split("/types/", 1)[1].removesuffix(".json")
                await wait_js(page, "window.fleetviz.conn.loader.layouts.has("
                                    f"{json.dumps(type_name)})")
            unexpected = [p for p in problems if "WebSocket" not in p]
            refused = [p for p in unexpected if "ERR_CONNECTION_REFUSED" in p]
            assert len(refused) <= len(on_a) and len(refused) == len(unexpected), unexpected
        finally:
            await context.close()
            await robot.stop()
