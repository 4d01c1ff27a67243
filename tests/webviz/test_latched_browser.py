"""A page that opens long after a latched map was published shows it (real relay, real
Chromium): the relay keeps the last latched message per sender and topic and gives it to a
late subscriber; the page must draw a message it receives only once."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import pytest

from fleetctl.wire.compression import CompressionCodec, compress
from fleetctl.wire.metadata import read_metadata
from tests.support import wait_until
from tests.webviz.conftest import webviz_server
from tests.webviz.fleet import OPERATOR_TOKEN
from tests.webviz.pixels import drawn_fraction_within
from tests.webviz.scripted import TF_TYPE, grid_values, scripted_fleet, tf_values
from tests.webviz.test_browser import MAP_BG, TIMEOUT_MS, sign_in, wait_js, watch_errors

pytestmark = pytest.mark.browser

GRID_TYPE = "nav_msgs/msg/OccupancyGrid"
# The case is a page opened 30 s after the map; the order is what matters
# (published, publisher still connected, then the page subscribes), so a shorter wall time.
LATE_S = 3.0


async def test_a_late_page_shows_the_latched_map(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    async with scripted_fleet(tmp_path) as relay:
        r1 = relay.robots["r1"]
        # Sent once: a 200 x 200 map deflate-compressed (as a robot sends big latched
        # messages), and the static TF, both latched; nothing is sent again.
        plain = r1.encode(GRID_TYPE, "/map", grid_values(size=200, resolution_m=0.05),
                          latched=True)
        await r1.send(compress(plain, codec=CompressionCodec.DEFLATE, topic="/r1/map",
                               no_drop=False, frame_codec=relay.codec))
        await r1.send(r1.encode(TF_TYPE, "/tf_static",
                                tf_values([("map", "odom", (1.0, 0.0, 0.0), 0.0)]), latched=True))
        published = time.monotonic()
        await wait_until(lambda: relay.server.metrics.latched_messages >= 2, 10)

        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport={"width": 1400, "height": 1100})
        problems = watch_errors(page)
        frames: list[bytes] = []
        page.on("websocket", lambda ws: ws.on(
            "framereceived", lambda p: frames.append(p) if isinstance(p, bytes) else None))
        await sign_in(page, web.url, OPERATOR_TOKEN)
        # The scenario's delay (not synchronization: the map was stored, checked above).
        await asyncio.sleep(max(0.0, LATE_S - (time.monotonic() - published)))
        await page.goto(web.url + "#/robot/r1")

        await wait_js(page, "fleetviz.views.map.grid !== null")
        assert time.monotonic() - published >= LATE_S
        assert await drawn_fraction_within(page.locator("#map-canvas"), MAP_BG, 0.25) > 0.25
        grid = await page.evaluate("[fleetviz.views.map.grid.width, "
                                   "fleetviz.views.map.grid.height]")
        assert grid == [200, 200]
        # The 3D scene has it too, in the map frame, with the latched static TF.
        await wait_js(page, "fleetviz.views.scene.placement('/r1/map')?.visible === true")
        await page.locator("#tf-tree li[data-frame='odom']").wait_for(timeout=TIMEOUT_MS)
        # What reached the page is the robot's one map, marked latched, inflated by Chromium.
        maps = [read_metadata(f) for f in frames if read_metadata(f).topic == "/r1/map"]
        assert len(maps) == 1 and maps[0].latched, maps
        assert await page.evaluate("fleetviz.conn.stats.decompressed") >= 1
        assert await page.evaluate("fleetviz.conn.stats.droppedNoLayout") == 0
        assert await page.evaluate("fleetviz.conn.health.topics.get('/r1/map').received") == 1
        assert not problems, problems
