"""The canvases an operator presses on stay where they are while the page's text changes
(a real relay, scripted WebSocket robots, headless Chromium).

An operator hovers over the map, then presses: a status line that wrapped in that instant
moved the map by a line (~20 px) and sent the goal ~0.5 m off. Here everything that says
something live changes while the map's and the scene's boxes are read at every animation
frame: video counters climbing, its picture frozen behind a lost frame (a long label in the
panel's title), a second video topic (its selector), a camera and a video
of another aspect ratio, a topic the page cannot decompress (its panel's note), the scene's
fixed frame, panels going quiet ("no data for N s"), the robot going offline ("offline,
last seen N s ago"), the relay going away and coming back (the banner, the header's
state), with a 49-character robot name in windows 1024 and 800 px wide.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerConfig
from fleetctl.wire.compression import CompressionCodec, compress
from tests.webviz.conftest import webviz_server
from tests.webviz.samples import header, pose_values, scan_values
from tests.webviz.scripted import TF_TYPE, VideoFeed, scripted_fleet, tf_values
from tests.webviz.test_browser import TIMEOUT_MS, open_robot_page, wait_js, watch_errors
from tests.webviz.video import encode

pytestmark = pytest.mark.browser

LONG = "warehouse_north_autonomous_forklift_unit_0017_bay"  # 49 characters
SCAN = "sensor_msgs/msg/LaserScan"
ODOM = "nav_msgs/msg/Odometry"
JPEG = "sensor_msgs/msg/CompressedImage"
# A directory for a full-page screenshot at each width, to look at (not docs/screenshots).
SCREENSHOTS = os.environ.get("FLEETCTL_WEBVIZ_LAYOUT_SHOTS")

# Each animation frame: the map's and the scene's boxes on the screen, and the scroll.
_RECORD = """() => {
  const rows = (window.__boxes = []);
  const box = (sel) => { const r = document.querySelector(sel).getBoundingClientRect();
                         return [r.x, r.y, r.width, r.height].map((v) => v.toFixed(2)).join(","); };
  const step = () => {
    if (window.__boxes !== rows) return;
    const boxes = `map ${box("#map-canvas")} scene ${box("#scene-canvas")}`;
    rows.push([`${boxes} scroll ${scrollX},${scrollY}`, window.__phase]);
    requestAnimationFrame(step);
  };
  step();
}"""


def jpeg_values(width: int, height: int) -> dict[str, Any]:
    buf = io.BytesIO()
    Image.new("RGB", (width, height), (200, 40, 40)).save(buf, "JPEG")
    return {"header": header("camera"), "format": "jpeg",
            "data": np.frombuffer(buf.getvalue(), dtype=np.uint8)}


def odom_values() -> dict[str, Any]:
    return {"header": header("odom"), "child_frame_id": "base_link",
            "pose": {"pose": pose_values(1.0, 2.0, 0.0)},
            "twist": {"twist": {"linear": {"x": 0.4}}}}


def moves(boxes: list[list[str]]) -> str:
    """The boxes in order, each change once, with what the test was doing then."""
    return "\n".join(f"{phase}: {b}" for i, (b, phase) in enumerate(boxes)
                     if i == 0 or b != boxes[i - 1][0])


async def phase(page: Any, what: str) -> None:
    """Name what happens next in the boxes' record."""
    await page.evaluate("w => { window.__phase = w; }", what)


@pytest.mark.parametrize("width", [1024, 800])
async def test_map_and_scene_hold_still_while_the_page_text_changes(
    tmp_path: Path, browser: Any, webviz_factory: list[Any], width: int
) -> None:
    async with scripted_fleet(tmp_path, (LONG,)) as relay:
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport={"width": width, "height": 800})
        problems = watch_errors(page)
        robot = relay.robots[LONG]
        full = f"/{LONG}"
        await open_robot_page(page, web.url, [f"{full}/scan", f"{full}/camera/video"], robot=LONG)
        # The map in the middle of the window, where an operator would aim at it.
        await page.evaluate("document.querySelector('#map-canvas')"
                            ".scrollIntoView({block: 'center'})")
        await phase(page, "start")
        await page.evaluate(_RECORD)

        # Sensors (the scan and odometry arrive, then stop) and a scene with a fixed frame.
        await phase(page, "sensors")
        robot.repeat(lambda: [
            robot.encode(SCAN, "/scan", scan_values(radius_m=3.0)),
            robot.encode(ODOM, "/odom", odom_values()),
            robot.encode(TF_TYPE, "/tf", tf_values([("map", "odom", (0, 0, 0), 0.0),
                                                    ("odom", "base_link", (1, 0, 0), 0.3)])),
        ])
        sensors = robot.tasks[-1]
        await page.locator("#robot-state", has_text="online").wait_for(timeout=TIMEOUT_MS)
        await page.locator("#scene-fixed", has_text="Fixed frame: map").wait_for(
            timeout=TIMEOUT_MS)
        # A camera of another aspect ratio than its canvas (16:9 on 4:3).
        await phase(page, "camera")
        robot.repeat(lambda: [robot.encode(JPEG, "/camera/image/compressed",
                                           jpeg_values(320, 180))], period_s=0.5)
        camera = robot.tasks[-1]
        await wait_js(page, "Number(document.querySelector('#camera-canvas').dataset.frames"
                            " || 0) >= 1")
        # Video of another aspect ratio, its counters climbing; then a second video topic
        await phase(page, "video")
        # (the panel's topic selector appears).
        units = encode("h264", 30, width=320, height=180, keyframe_every=10)
        video = VideoFeed(robot, "/camera/video", units, "h264")
        video.run(period_s=1 / 15)
        await wait_js(page, "Number(document.querySelector('#video-canvas').dataset.shown"
                            " || 0) >= 10")
        # A frame lost: the panel's title says the picture is old (a long label: it
        # wrapped the panel's title "Video" onto two lines in a demo run).
        await phase(page, "frozen video")
        await video.stop()
        video = VideoFeed(robot, "/camera/video", [u for u in units if not u.key], "h264")
        await video.send_next(skip=True)  # and no keyframe after it
        video.run(period_s=1 / 15)
        await page.locator("#panel-video h3 .age", has_text="waiting for a keyframe").wait_for(
            timeout=TIMEOUT_MS)
        await phase(page, "second video")
        await VideoFeed(robot, "/camera/image", units, "h264").send_next()
        await page.locator("#video-topic").wait_for(state="visible", timeout=TIMEOUT_MS)
        # A topic compressed in a way the page cannot decode: its panel says so.
        await phase(page, "zstd")
        plain = robot.encode(SCAN, "/scan", scan_values(beams=2000, radius_m=3.0))
        await robot.send(compress(plain, codec=CompressionCodec.ZSTD, topic=f"{full}/scan",
                                  no_drop=False, frame_codec=robot.codec))
        await page.locator("#panel-scan .panel-note", has_text="zstd").wait_for(
            timeout=TIMEOUT_MS)
        # Quiet: "no data for N s" in the titles; then offline, its age counting up.
        await phase(page, "quiet")
        sensors.cancel()
        camera.cancel()
        await page.locator("#panel-scan.stale h3 .age", has_text="no data for").wait_for(
            timeout=TIMEOUT_MS)
        await video.stop()
        await phase(page, "offline")
        await robot.stop()
        await page.locator("#robot-state", has_text="offline, last seen").wait_for(
            timeout=TIMEOUT_MS)
        await wait_js(page, "/last seen [2-9]/.test("
                            "document.querySelector('#robot-state').textContent)")
        # The relay goes away (the banner, the header's state) and comes back.
        await phase(page, "relay down")
        port = relay.server.port
        config: ServerConfig = relay.server.config
        await relay.server.stop()
        await page.locator("#banner", has_text="Disconnected from the fleet server").wait_for(
            state="visible", timeout=TIMEOUT_MS)
        again = RelayServer(ServerConfig(**{**config.__dict__, "listen_port": port}),
                            relay.server.auth)
        await phase(page, "relay back")
        await again.start()
        try:
            await page.locator("#conn-state", has_text="open").wait_for(timeout=TIMEOUT_MS)
            await page.locator("#banner").wait_for(state="hidden", timeout=TIMEOUT_MS)
            await wait_js(page, "Number(document.querySelector('#robot-state').textContent"
                                ".match(/last seen (\\d+)/)?.[1]) >= 1")
            if SCREENSHOTS:
                await page.screenshot(path=f"{SCREENSHOTS}/layout-{width}.png", full_page=True)
        finally:
            await again.stop()
        boxes: list[list[str]] = await page.evaluate("window.__boxes.splice(0)")
        assert len(boxes) > 100, len(boxes)  # read at every frame for seconds
        assert len({b for b, _ in boxes}) == 1, moves(boxes)
        # What an ellipsis cuts stays in the title.
        assert await page.get_attribute("#robot-name", "title") == LONG
        untitled = await page.evaluate("[...document.querySelectorAll('.oneline')]"
                                       ".filter(e => e.title !== e.textContent.trim())"
                                       ".map(e => e.id)")
        assert untitled == []
        # The attempts while the relay was away are expected; nothing else is.
        assert [p for p in problems if "ERR_CONNECTION_REFUSED" not in p] == []


# Each animation frame: the box, in page coordinates (a click may scroll the window), of
# everything an operator presses on or drags.
PRESSABLE = ("#scene-canvas", "#video-canvas", "#camera-canvas", "#scan-canvas",
             "#cloud-canvas", "#map-canvas", "#tool-goal", "#gps-map")
_RECORD_PRESSABLE = """(sels) => {
  const rows = (window.__held = []);
  const box = (sel) => { const r = document.querySelector(sel).getBoundingClientRect();
                         const v = [r.x + scrollX, r.y + scrollY, r.width, r.height];
                         return `${sel} ${v.map((n) => n.toFixed(2)).join(",")}`; };
  const step = () => {
    if (window.__held !== rows) return;
    rows.push([sels.map(box).join(" "), window.__phase]);
    requestAnimationFrame(step);
  };
  step();
}"""


def gps_values() -> dict[str, Any]:
    return {"header": header("gps"), "status": {"status": 0, "service": 1},
            "latitude": 30.2862, "longitude": -97.7365, "altitude": 150.5,
            "position_covariance": np.ones(9), "position_covariance_type": 2}


# Where the panels stack: 3 columns (the GPS panel in the row under the map's), 2 (the GPS
# panel under the map), 1 (a phone: odometry, then GPS, under the map).
@pytest.mark.parametrize(("width", "height"), [(1024, 800), (800, 800), (390, 844)])
async def test_pressable_panels_hold_still_while_the_map_panel_and_odometry_grow(
    tmp_path: Path, browser: Any, webviz_factory: list[Any], width: int, height: int
) -> None:
    # The pose form opening under the map (and its error line, the aiming line) grew the
    # map's panel, so the panels below moved: the GPS map an operator was dragging went
    # down by the form's height. Likewise the odometry's first message above the GPS panel
    # on a phone.
    async with scripted_fleet(tmp_path, ("r1",)) as relay:
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport={"width": width, "height": height})
        problems = watch_errors(page)
        robot = relay.robots["r1"]
        await open_robot_page(page, web.url, ["/r1/odom", "/r1/gps/fix"])
        await wait_js(page, "fleetviz.views.gps.map !== undefined")
        await page.locator("#panel-odom .panel-wait").wait_for(timeout=TIMEOUT_MS)
        await phase(page, "start")
        await page.evaluate(_RECORD_PRESSABLE, list(PRESSABLE))

        await phase(page, "odometry and GPS")
        robot.repeat(lambda: [robot.encode(ODOM, "/odom", odom_values()),
                              robot.encode("sensor_msgs/msg/NavSatFix", "/gps/fix",
                                           gps_values())], period_s=0.2)
        await page.locator("#odom-text", has_text="heading").wait_for(timeout=TIMEOUT_MS)
        await page.locator("#gps-text", has_text="lat 30.286200").wait_for(timeout=TIMEOUT_MS)
        await page.locator("#panel-odom .panel-wait").wait_for(state="hidden",
                                                               timeout=TIMEOUT_MS)
        await phase(page, "goal tool armed")
        await page.click("#tool-goal")
        await page.locator("#pose-form").wait_for(state="visible", timeout=TIMEOUT_MS)
        await page.locator("#command-status", has_text="press on the map").wait_for(
            timeout=TIMEOUT_MS)
        await phase(page, "aiming")
        await page.hover("#map-canvas")
        await page.locator("#command-status", has_text="Navigation goal at x=").wait_for(
            timeout=TIMEOUT_MS)
        await phase(page, "a bad field")
        await page.fill("#pose-y", "abc")
        await page.press("#pose-y", "Enter")
        await page.locator("#pose-error", has_text='y: "abc"').wait_for(timeout=TIMEOUT_MS)
        await phase(page, "cancelled")
        await page.keyboard.press("Escape")
        await page.locator("#pose-form").wait_for(state="hidden", timeout=TIMEOUT_MS)
        await phase(page, "typed and sent")
        await page.click("#tool-goal")
        await page.fill("#pose-x", "12.5")
        await page.fill("#pose-y", "-3")
        await page.fill("#pose-yaw", "180")
        await page.press("#pose-yaw", "Enter")
        await page.locator("#command-status", has_text="Sent navigation goal").wait_for(
            timeout=TIMEOUT_MS)
        await page.locator("#pose-form").wait_for(state="hidden", timeout=TIMEOUT_MS)
        boxes: list[list[str]] = await page.evaluate("window.__held.splice(0)")
        if SCREENSHOTS:  # after the record: a full-page shot lays the page out again
            await page.click("#tool-goal")  # armed, a field refused: the most said
            await page.fill("#pose-y", "abc")
            await page.press("#pose-y", "Enter")
            await page.screenshot(path=f"{SCREENSHOTS}/held-{width}.png", full_page=True)
        assert len(boxes) > 30, len(boxes)
        assert len({b for b, _ in boxes}) == 1, moves(boxes)
        assert problems == []
