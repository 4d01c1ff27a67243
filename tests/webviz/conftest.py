"""Fixtures of the webviz tests: the page's HTTP server and a headless Debian Chromium."""

from __future__ import annotations

import shutil
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

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


@pytest.fixture
async def page(browser: Any, webviz_factory: list[BackgroundWebviz]) -> AsyncIterator[Any]:
    """A page on the webviz origin (no relay), for tests that import the page's modules;
    fails the test on any uncaught error in it."""
    web = webviz_server(None).start()
    webviz_factory.append(web)
    p = await browser.new_page()
    errors: list[str] = []
    p.on("pageerror", lambda e: errors.append(str(e)))
    await p.goto(web.url + "config.json")  # any page of the origin: modules load from it
    yield p
    assert not errors, errors
    await p.close()
