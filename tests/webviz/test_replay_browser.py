"""A replayed robot on the page (real relay, scripted WebSocket robots, headless
Chromium): ``fleetctl replay`` sends a recorded husky1 as ``husky1_replay``, which the
page listed and opened as one more live robot, its goal tools offered as if a robot would
act on them."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from fleetctl.wire.control import encode_status
from tests.webviz.fleet import OPERATOR_TOKEN
from tests.webviz.test_browser import SCREENSHOTS, TIMEOUT_MS, sign_in
from tests.webviz.test_panels_browser import fleet_page

pytestmark = pytest.mark.browser


async def test_a_replay_is_marked_in_the_list_and_on_its_page(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    async with fleet_page(tmp_path, browser, webviz_factory, ("husky1", "husky1_replay"),
                          viewport=(1024, 768)) as (relay, web, page, problems):
        for name, robot in relay.robots.items():  # the registry lists robots that sent
            robot.repeat(lambda n=name: [encode_status(
                n, status="mapping hall 2", is_ok=True, battery_level=0.8,
                location="hall 2", codec=relay.codec)])
        await sign_in(page, web.url, OPERATOR_TOKEN)
        replay_row = page.locator('#robots tr[data-robot="husky1_replay"]')
        live_row = page.locator('#robots tr[data-robot="husky1"]')
        await replay_row.wait_for(timeout=TIMEOUT_MS)
        await live_row.wait_for(timeout=TIMEOUT_MS)
        assert await replay_row.locator(".replay-of").text_content() == "replay of husky1"
        assert await live_row.locator(".replay-of").count() == 0
        if SCREENSHOTS:
            await page.screenshot(path=os.path.join(SCREENSHOTS, "replay-list.png"))

        await page.goto(web.url + "#/robot/husky1_replay")
        await page.locator("#robot-replay").wait_for(timeout=TIMEOUT_MS)
        assert await page.text_content("#robot-replay") == "replay of husky1"
        note = await page.text_content("#replay-note")
        assert "no robot acts on" in note and "husky1_replay" in note
        assert "replay" in await page.get_attribute("#tool-goal", "title")
        if SCREENSHOTS:
            await page.screenshot(path=os.path.join(SCREENSHOTS, "replay-robot.png"),
                                  full_page=True)

        await page.goto(web.url + "#/robot/husky1")  # the live robot: no mark, no note
        await page.locator("#robot-replay").wait_for(state="hidden", timeout=TIMEOUT_MS)
        assert await page.is_hidden("#replay-note")
        assert "replay" not in await page.get_attribute("#tool-goal", "title")
        assert not problems, problems
