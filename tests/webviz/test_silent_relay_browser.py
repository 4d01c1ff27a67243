"""A relay the page cannot hear any more (headless Chromium, a real relay, a real TCP path
that goes silent): the page gives the socket up, says so, and is back when the path is.

A hung relay, or a dead path the TCP stack does not report (a server host that lost power,
a laptop that changed networks), left the page saying "open", the robot "online", and its
panels as they were, for as long as the browser kept the socket: minutes. The path here is
a TCP relay in the test that stops forwarding (both ways, connections kept open, new ones
held), as a dead network path does.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from tests.webviz.conftest import webviz_server
from tests.webviz.samples import scan_values
from tests.webviz.scripted import scripted_fleet
from tests.webviz.test_browser import TIMEOUT_MS, open_robot_page, wait_js, watch_errors

pytestmark = pytest.mark.browser

SCAN = "sensor_msgs/msg/LaserScan"
SILENT_MS = 15_000  # js/connection.js SILENT_MS
GIVE_UP_TIMEOUT_MS = SILENT_MS + TIMEOUT_MS


class SilentPath:
    """A TCP relay to *upstream_port* that can go silent: while :attr:`quiet`, no byte is
    forwarded either way and new connections are accepted but held; nothing is closed."""

    def __init__(self, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        self.open_path = asyncio.Event()
        self.open_path.set()
        self.tasks: set[asyncio.Task[None]] = set()
        self.writers: list[asyncio.StreamWriter] = []
        self.port = 0

    @property
    def quiet(self) -> bool:
        return not self.open_path.is_set()

    @quiet.setter
    def quiet(self, value: bool) -> None:
        if value:
            self.open_path.clear()
        else:
            self.open_path.set()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(ConnectionError):
            while data := await reader.read(65536):
                await self.open_path.wait()
                writer.write(data)
                await writer.drain()
        writer.close()

    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writers.append(writer)
        await self.open_path.wait()
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.upstream_port)
        self.writers.append(up_writer)
        await asyncio.gather(self._pump(reader, up_writer), self._pump(up_reader, writer))

    def _spawn(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.ensure_future(self._connection(reader, writer))
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    @contextlib.asynccontextmanager
    async def running(self) -> AsyncIterator[SilentPath]:
        server = await asyncio.start_server(self._spawn, "127.0.0.1", 0)
        self.port = server.sockets[0].getsockname()[1]
        try:
            yield self
        finally:
            server.close()
            for task in list(self.tasks):
                task.cancel()
            await asyncio.gather(*self.tasks, return_exceptions=True)
            for w in self.writers:
                w.close()
            await server.wait_closed()


async def test_a_silent_relay_is_given_up_said_and_rejoined(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    async with scripted_fleet(tmp_path) as relay, SilentPath(relay.server.port).running() as path:
        web = webviz_server(f"ws://127.0.0.1:{path.port}/").start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport={"width": 1280, "height": 800})
        problems = watch_errors(page)
        r1 = relay.robots["r1"]
        await open_robot_page(page, web.url, ["/r1/scan"])
        r1.repeat(lambda: [r1.encode(SCAN, "/scan", scan_values(radius_m=3.0))])
        await wait_js(page, "document.querySelector('#scan-canvas').dataset.beams")
        await page.locator("#robot-state", has_text="online").wait_for(timeout=TIMEOUT_MS)

        path.quiet = True  # the relay and the robot go on; the page hears nothing
        # Given up after SILENT_MS: said while the next attempt waits (its upgrade is held
        # too, and given up the same way).
        await page.locator("#banner", has_text=(
            "(the last connection: no answer from the server for 1")).wait_for(
            timeout=GIVE_UP_TIMEOUT_MS)
        assert await page.text_content("#conn-state") != "open"
        # What the page knew of the robot is as old as the socket: not "online".
        assert await page.text_content("#robot-state") == (
            "state unknown: not connected to the fleet server")
        assert await page.is_visible("#panel-scan.stale h3 .age")

        path.quiet = False
        await page.locator("#conn-state", has_text="open").wait_for(timeout=GIVE_UP_TIMEOUT_MS)
        await page.locator("#banner").wait_for(state="hidden", timeout=TIMEOUT_MS)
        await page.locator("#robot-state", has_text="online").wait_for(timeout=TIMEOUT_MS)
        await page.locator("#panel-scan.stale").wait_for(state="detached", timeout=TIMEOUT_MS)
        assert await page.locator("#panel-scan h3 .age").text_content() == ""
        assert not problems, problems
