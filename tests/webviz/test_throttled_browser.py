"""The page in Chromium against a real relay whose failed-login budget for the page's
address is spent (docs/webviz.md, "Too many failed sign-ins"): the banner says so in
words, the page waits the relay's Retry-After, then signs in by itself."""

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
from tests.webviz.fleet import OPERATOR_TOKEN, write_auth_map
from tests.webviz.test_browser import TIMEOUT_MS, wait_js

pytestmark = pytest.mark.browser


async def test_a_throttled_page_says_so_waits_and_signs_in(
        tmp_path: Path, browser: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    # The browser connects from 127.0.0.1, which has no budget (docs/security.md): here
    # it has one, of 3 failures, then one per 2 s (Retry-After 2).
    monkeypatch.setattr(loginbudget, "UNLIMITED", frozenset())
    monkeypatch.setattr(loginbudget, "FAILURES_BURST", 3)
    monkeypatch.setattr(loginbudget, "FAILURE_INTERVAL_S", 2.0)
    cert, key = self_signed(tmp_path / "tls")
    auth = load_auth_map(write_auth_map(tmp_path / "auth.yaml", {}))
    config = ServerConfig(
        listen_host="127.0.0.1", listen_port=0, auth_map=tmp_path / "auth.yaml", database=None,
        web=WebConfig(tls_cert=cert, tls_key=key, listen_host="127.0.0.1", listen_port=0),
    )
    async with RelayServer(config, auth) as server:
        for _ in range(3):  # a script at the same address with a stale token
            async with client(server, token="stale") as ws:
                assert await closed_code(ws) == 4401
        context = await browser.new_context(ignore_https_errors=True)
        try:
            page = await context.new_page()
            assert server.web_url is not None
            await page.goto(server.web_url)
            await page.fill("#token", OPERATOR_TOKEN)
            await page.click("#signin-button")
            banner = page.locator("#banner", has_text="Too many failed sign-ins from your "
                                  "network address")
            await banner.wait_for(timeout=TIMEOUT_MS)
            text = await banner.text_content()
            # Retry-After is whole seconds up to the refill (2 s), 1 or 2 by now; the page
            # waits that plus up to 20 %.
            assert text is not None and re.search(r"Trying again in about (1\.[0-2]|2\.[0-4]) s",
                                                  text), text
            assert OPERATOR_TOKEN not in text
            assert await page.text_content("#conn-state") == "throttled"
            await wait_js(page, "document.querySelector('#conn-state').textContent === 'open'")
            assert await page.is_hidden("#banner")
        finally:
            await context.close()
        # The refused upgrade and the page's question, each refused unhashed; nothing
        # sooner than the hint (a retry at the page's 0.25 s backoff would add more).
        assert server.core.logins.refusals == 2
        assert server.core.logins.failures == 3
