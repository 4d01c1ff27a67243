"""Fixtures of the webviz tests: the page's HTTP server and a headless Debian Chromium."""

from __future__ import annotations

import shutil
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest

from fleetctl.webviz.config import WebvizConfig
from fleetctl.webviz.httpserver import BackgroundWebviz
from fleetctl.webviz.layouts import LayoutCache
from fleetctl.wire.registry import TypeRegistry

CHROMIUM = Path("/usr/bin/chromium")


def webviz_server(server_url: str | None, **kw: object) -> BackgroundWebviz:
    config = WebvizConfig(listen_host="127.0.0.1", listen_port=0, server_url=server_url, **kw)  # type: ignore[arg-type]
    return BackgroundWebviz(config, LayoutCache(TypeRegistry.default()))


@pytest.fixture
def webviz_factory() -> Iterator[list[BackgroundWebviz]]:
    started: list[BackgroundWebviz] = []
    yield started
    for s in started:
        s.stop()


@pytest.fixture
async def browser() -> AsyncIterator[object]:
    if not CHROMIUM.exists() or shutil.which("chromium") is None:
        pytest.fail("Debian chromium is not installed: apt-get install chromium (scripts/setup.sh)")
    from playwright.async_api import async_playwright

    async with async_playwright() as p:
        b = await p.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox"])
        try:
            yield b
        finally:
            await b.close()
