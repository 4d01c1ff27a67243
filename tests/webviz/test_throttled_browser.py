"""The page in Chromium against a real relay whose failed-login budget for the page's
address is spent (docs/webviz.md, "Too many failed sign-ins"): the banner says so in
words, the page waits the relay's Retry-After, then signs in by itself; on the relay's
own origin and on another (the page of ``fleetctl webviz``)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from fleetctl.server import loginbudget
from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import load_auth_map
from fleetctl.server.config import ServerConfig, WebConfig
from tests.server.certs import self_signed
from tests.server.conftest import client
from tests.server.test_app import closed_code
from tests.webviz.conftest import webviz_server
from tests.webviz.fleet import OPERATOR_TOKEN, write_auth_map
from tests.webviz.test_browser import TIMEOUT_MS, wait_js, watch_errors

pytestmark = pytest.mark.browser


@pytest.fixture
def budgeted_loopback(monkeypatch: pytest.MonkeyPatch) -> None:
    """The browser connects from 127.0.0.1, which has no budget (docs/security.md): here
    it has one, of 3 failures, then one per 2 s (Retry-After 2)."""
    monkeypatch.setattr(loginbudget, "UNLIMITED", frozenset())
    monkeypatch.setattr(loginbudget, "FAILURES_BURST", 3)
    monkeypatch.setattr(loginbudget, "FAILURE_INTERVAL_S", 2.0)


def relay(tmp_path: Path) -> RelayServer:
    """A relay with its web listener (the page on its own origin) and no robots."""
    cert, key = self_signed(tmp_path / "tls")
    auth = load_auth_map(write_auth_map(tmp_path / "auth.yaml", {}))
    config = ServerConfig(
        listen_host="127.0.0.1", listen_port=0, auth_map=tmp_path / "auth.yaml", database=None,
        web=WebConfig(tls_cert=cert, tls_key=key, listen_host="127.0.0.1", listen_port=0),
    )
    return RelayServer(config, auth)


async def spend_budget(server: RelayServer) -> None:
    for _ in range(3):  # a script at the same address with a stale token
        async with client(server, token="stale") as ws:
            assert await closed_code(ws) == 4401


async def says_throttled_then_signs_in(browser: Any, url: str, server: RelayServer) -> None:
    """Sign in on the page at *url* once *server*'s budget for loopback is spent: the
    banner says the throttle in words with the relay's hint, then the page signs in by
    itself once the hint has passed."""
    context = await browser.new_context(ignore_https_errors=True)
    try:
        page = await context.new_page()
        problems = watch_errors(page)
        await page.goto(url)
        await page.fill("#token", OPERATOR_TOKEN)
        # Spent only now: the budget refills one failure per 2 s, and loading the page
        # on a busy machine took longer than that (the page then signed in at once).
        await spend_budget(server)
        await page.click("#signin-button")
        banner = page.locator("#banner", has_text="Too many failed sign-ins from your "
                              "network address")
        try:
            await banner.wait_for(timeout=TIMEOUT_MS)
        except Exception as err:
            shown = await page.evaluate("[document.querySelector('#conn-state').textContent,"
                                        " document.querySelector('#banner').textContent]")
            raise AssertionError(f"no throttle said: state, banner = {shown}, {problems}") from err
        text = await banner.text_content()
        # Retry-After is whole seconds up to the refill (2 s), 1 or 2 by now; the page
        # waits that plus up to 20 %.
        assert text is not None and re.search(r"Trying again in about (1\.[0-2]|2\.[0-4]) s",
                                              text), text
        assert OPERATOR_TOKEN not in text
        assert await page.text_content("#conn-state") == "throttled"
        await wait_js(page, "document.querySelector('#conn-state').textContent === 'open'")
        assert await page.is_hidden("#banner")
        # Chromium's console lines about the refused upgrade and the probe's 429 are
        # expected; an exception in the page is not.
        assert [p for p in problems if p.startswith("pageerror")] == [], problems
    finally:
        await context.close()


@pytest.mark.usefixtures("budgeted_loopback")
async def test_a_throttled_page_says_so_waits_and_signs_in(
        tmp_path: Path, browser: Any) -> None:
    async with relay(tmp_path) as server:
        assert server.web_url is not None
        await says_throttled_then_signs_in(browser, server.web_url, server)
        # The refused upgrade, refused unhashed; nothing sooner than the hint (a retry at
        # the page's 0.25 s backoff would add more). The page's question is no login.
        assert server.core.logins.refusals == 1
        assert server.core.logins.failures == 3


@pytest.mark.usefixtures("budgeted_loopback")
async def test_a_page_on_another_origin_says_so_too(
        tmp_path: Path, browser: Any, webviz_factory: list[Any]) -> None:
    # The page from `fleetctl webviz` (http://127.0.0.1:A), the relay's WebSocket port
    # (ws://127.0.0.1:B): before /login-budget, this page could only say "Disconnected".
    async with relay(tmp_path) as server:
        web = webviz_server(server.url).start()
        webviz_factory.append(web)
        assert web.url.split("/")[2] != server.url.split("/")[2]  # another origin
        await says_throttled_then_signs_in(browser, web.url, server)
        assert (server.core.logins.refusals, server.core.logins.failures) == (1, 3)
