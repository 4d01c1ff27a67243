"""What the robot page's panels say and show when a robot team's topics are not the page's
(a real relay, scripted WebSocket robots, headless Chromium): a panel that has drawn
nothing names the topic it waits for, a robot switch clears the last robot's pictures, the
scan is scaled to what it sees with labelled rings, and a phone's page is no wider than
its screen."""

from __future__ import annotations

import contextlib
import io
import re
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from fleetctl.wire.control import encode_status, encode_subscription
from tests.webviz.conftest import webviz_server
from tests.webviz.fleet import OPERATOR_TOKEN
from tests.webviz.msgs import make
from tests.webviz.pixels import colored_pixels
from tests.webviz.samples import header, pose_values, scan_values
from tests.webviz.scripted import Relay, scripted_fleet
from tests.webviz.test_browser import (
    TIMEOUT_MS,
    open_robot_page,
    pixels,
    sign_in,
    wait_js,
    watch_errors,
)

pytestmark = pytest.mark.browser

SCAN = "sensor_msgs/msg/LaserScan"
JPEG = "sensor_msgs/msg/CompressedImage"
IMAGE = "sensor_msgs/msg/Image"
ODOM = "nav_msgs/msg/Odometry"


def jpeg_values() -> dict[str, Any]:
    buf = io.BytesIO()
    Image.new("RGB", (64, 48), (200, 40, 40)).save(buf, "JPEG")
    return {"header": header("camera"), "format": "jpeg",
            "data": np.frombuffer(buf.getvalue(), dtype=np.uint8)}


def raw_image_values() -> dict[str, Any]:
    return {"header": header("camera"), "height": 16, "width": 16, "encoding": "rgb8",
            "is_bigendian": 0, "step": 48, "data": np.full(16 * 48, 90, dtype=np.uint8)}


def odom_values() -> dict[str, Any]:
    return {"header": header("odom"), "child_frame_id": "base_link",
            "pose": {"pose": pose_values(1.0, 2.0, 0.0)},
            "twist": {"twist": {"linear": {"x": 0.4}}}}


def scan_of(radius_m: float, range_max: float = 30.0) -> dict[str, Any]:
    return {**scan_values(radius_m=radius_m), "range_max": range_max}


def note(panel: str) -> str:
    return f"#panel-{panel} .panel-wait"


@contextlib.asynccontextmanager
async def fleet_page(tmp_path: Path, browser: Any, webviz_factory: list[Any],
                     names: tuple[str, ...] = ("r1",), viewport: tuple[int, int] = (1280, 800),
                     ) -> AsyncIterator[tuple[Relay, Any, Any, list[str]]]:
    """A scripted fleet of *names*, its page server and a new browser page (not signed
    in yet); yields the relay, the page server, the page and the page's problems."""
    async with scripted_fleet(tmp_path, names) as relay:
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
        yield relay, web, page, watch_errors(page)


async def test_empty_panels_name_their_topic_and_a_robot_switch_clears_them(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    # r1: a camera and a scan where the page looks, a raw camera where the Video panel
    # looks (not sent as video), no cloud; r2: only odometry. Before, r1's cloud panel was
    # a black box, the Video panel said only "no video yet", and r2's page went on showing
    # r1's camera frame and scan.
    async with fleet_page(tmp_path, browser, webviz_factory, ("r1", "r2")) as (
            relay, web, page, problems):
        r1, r2 = relay.robots["r1"], relay.robots["r2"]
        await page.goto(web.url)
        await page.locator("#token").wait_for(timeout=TIMEOUT_MS)
        assert await page.is_hidden("#signout")  # nobody to sign out yet
        await sign_in(page, web.url, OPERATOR_TOKEN)
        assert await page.is_visible("#signout")
        r1.repeat(lambda: [r1.encode(JPEG, "/camera/image/compressed", jpeg_values()),
                           r1.encode(SCAN, "/scan", scan_of(3.0)),
                           r1.encode(IMAGE, "/camera/image_raw", raw_image_values())])
        r2.repeat(lambda: [r2.encode(ODOM, "/odom", odom_values())])
        await page.goto(web.url + "#/robot/r1")
        await wait_js(page, "Number(document.querySelector('#camera-canvas').dataset.frames"
                            " || 0) >= 1 && document.querySelector('#scan-canvas').dataset.beams")
        # The waiting notes go with the panel's first message, not at the next
        # once-a-second render: "Nothing on ... yet" lay over a picture already drawn.
        assert await page.is_hidden(note("camera")) and await page.is_hidden(note("scan"))
        await page.locator(note("cloud"), has_text=(
            "Nothing on /r1/points (sensor_msgs/msg/PointCloud2) yet. The robot's /points is "
            "shown here; another topic needs remote_topic: /r1/points in its publish entry."
        )).wait_for(timeout=TIMEOUT_MS)
        await page.locator(note("video"), has_text=(
            "/r1/camera/image_raw arrives as sensor_msgs/msg/Image, not as video: add video: "
            "{codec: h264} to its publish entry")).wait_for(timeout=TIMEOUT_MS)
        assert await page.locator("#video-status").text_content() == "no video yet"
        await page.locator(note("odom"), has_text="Nothing on /r1/odom").wait_for(
            timeout=TIMEOUT_MS)
        assert await page.is_hidden(note("camera")) and await page.is_hidden(note("scan"))
        assert await pixels(page, "#camera-canvas") > 1000
        # The note lies over the canvas: the panel is as tall with it as without it.
        shown = (await page.locator("#panel-cloud").bounding_box())["height"]
        await page.locator(note("cloud")).evaluate("e => e.hidden = true")
        assert (await page.locator("#panel-cloud").bounding_box())["height"] == shown

        await page.goto(web.url + "#/robot/r2")
        await page.locator(note("camera"), has_text="Nothing on /r2/camera/image/compressed"
                           ).wait_for(timeout=TIMEOUT_MS)
        await page.locator(note("scan"), has_text="Nothing on /r2/scan").wait_for(
            timeout=TIMEOUT_MS)
        await page.locator("#odom-text", has_text="0.40 m/s").wait_for(timeout=TIMEOUT_MS)
        await page.locator(note("odom")).wait_for(state="hidden", timeout=TIMEOUT_MS)
        video_note = page.locator(note("video"), has_text=(
            "no video yet on /r2/camera/image_raw, /r2/camera/image or /r2/camera/video"))
        await video_note.wait_for(timeout=TIMEOUT_MS)
        # All of it shows, over the black picture: in the 3-line status box under it a
        # 300 px panel cut the sentence off.
        assert await video_note.evaluate("e => e.scrollHeight <= e.clientHeight + 1")
        box = await video_note.bounding_box()
        canvas = await page.locator("#video-canvas").bounding_box()
        assert box["y"] + box["height"] <= canvas["y"] + canvas["height"]
        # r1's picture and scan are gone (r1 keeps publishing; this page no longer asks):
        # every pixel of both canvases is the background.
        blank = ("sel => { const c = document.querySelector(sel);"
                 " const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
                 " let n = 0; for (let i = 0; i < d.length; i += 4)"
                 "   if (d[i] !== 16 || d[i + 1] !== 20 || d[i + 2] !== 24) n++;"
                 " return n; }")
        assert await page.evaluate(blank, "#camera-canvas") == 0
        assert await page.evaluate(blank, "#scan-canvas") == 0
        assert not problems, problems


async def test_the_scan_is_scaled_to_its_returns_with_labelled_rings(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    # A 30 m lidar in a 3 m room was drawn at range_max: a fifth of the panel, rings at
    # 1, 7, 13, 19, 25 m without a label.
    async with fleet_page(tmp_path, browser, webviz_factory) as (relay, web, page, problems):
        r1 = relay.robots["r1"]
        await open_robot_page(page, web.url, ["/r1/scan"])
        radius = [3.0]
        r1.repeat(lambda: [r1.encode(SCAN, "/scan", scan_of(radius[0]))], period_s=0.05)
        extent = "document.querySelector('#scan-canvas').dataset.extentM"
        await wait_js(page, f"{extent} === '5'")  # 3.5 m farthest return, 10 % margin
        assert await page.get_attribute("#scan-canvas", "data-ring-step-m") == "1"
        shot = await page.locator("#scan-canvas").screenshot()
        assert pixels_far_out(shot) > 50  # the returns reach far into the panel
        radius[0] = 12.0  # a door opens: the scale grows at once
        await wait_js(page, f"{extent} === '15'")
        assert await page.get_attribute("#scan-canvas", "data-ring-step-m") == "5"
        radius[0] = 3.0  # and shrinks back only after a run of small scans
        await wait_js(page, f"{extent} === '5'")
        assert not problems, problems


def pixels_far_out(png: bytes) -> int:
    """Scan-coloured pixels more than a third of the panel's half width from its centre."""
    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    h, w, _ = img.shape
    orange = (abs(img[..., 0] - 255) < 40) & (abs(img[..., 1] - 157) < 40) & (img[..., 2] < 90)
    yy, xx = np.mgrid[0:h, 0:w]
    far = np.hypot(yy - h / 2, xx - w / 2) > min(w, h) / 6
    return int((orange & far).sum())


async def test_a_phone_sized_page_is_no_wider_than_the_screen(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    # At 390 px the overview and link health tables made the page 540-570 px wide, and the
    # 3D scene beside its TF tree was 195 px wide with the tree cut off. A long robot name
    # (its topics ~90 characters) ran the title and the notes naming topics out of their
    # panels: the page was 626 px wide here, 1082 px in a 1024 px window.
    name = "warehouse_robot_north_building_aisle_12_unit_0007"
    async with fleet_page(tmp_path, browser, webviz_factory, (name,), viewport=(390, 844)) as (
            relay, web, page, problems):
        robot = relay.robots[name]
        await sign_in(page, web.url, OPERATOR_TOKEN)
        robot.repeat(lambda: [
            encode_status(name, status="docking at charger 3", is_ok=True, battery_level=0.5,
                          location="north hall, aisle 12", codec=relay.codec),
            robot.encode(SCAN, "/scan", scan_of(3.0)),
            robot.encode(JPEG, "/camera/image/compressed", jpeg_values())])
        await page.locator(f'#robots tr[data-robot="{name}"] td.state', has_text="online"
                           ).wait_for(timeout=TIMEOUT_MS)
        await wait_js(page, "document.querySelector('#robots').textContent.includes('msg/s')")
        width = "document.documentElement.scrollWidth"
        assert await page.evaluate(width) <= 390
        await page.goto(web.url + f"#/robot/{name}")
        await page.locator("#health tbody tr", has_text=f"/{name}/camera/image/compressed"
                           ).wait_for(timeout=TIMEOUT_MS)
        await page.locator(note("cloud"), has_text=f"Nothing on /{name}/points").wait_for(
            timeout=TIMEOUT_MS)
        assert await page.evaluate(width) <= 390
        overflowing = ("[...document.querySelectorAll('.panel, #robot .toolbar')]"
                       ".filter(e => e.offsetParent && e.scrollWidth > e.clientWidth + 1)"
                       ".map(e => e.id || e.className)")
        assert await page.evaluate(overflowing) == []
        # No TF from this robot: the fixed-frame choice still offers "auto" (it was empty).
        await wait_js(page, "document.querySelector('#scene-frame').options.length === 1")
        assert await page.text_content("#scene-frame") == "auto (map, odom, root)"
        await page.set_viewport_size({"width": 1024, "height": 700})
        await page.locator("#panel-odom .panel-wait").wait_for(timeout=TIMEOUT_MS)
        assert await page.evaluate(width) <= 1024
        assert await page.evaluate(overflowing) == []
        await page.set_viewport_size({"width": 390, "height": 844})
        scene = await page.locator("#scene-canvas").bounding_box()
        tree = await page.locator(".scene-side").bounding_box()
        assert scene["width"] > 300 and tree["width"] > 300  # stacked, each full width
        assert tree["y"] >= scene["y"] + scene["height"]
        assert not problems, problems


GOAL = "geometry_msgs/msg/PoseStamped"
GOAL_RGB = (239, 83, 80)  # #ef5350, the goal arrow
POSE_RGB = (255, 202, 40)  # #ffca28, the robot's arrow


async def test_the_map_marks_the_sent_goal_breaks_the_path_at_a_jump_and_pans(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    # After a goal was sent the map showed nothing of it, an initial pose drew a straight
    # path line across the map from the old place, and a map far from 0, 0 was out of reach
    # (no pan); the tool buttons did not show that they were armed.
    async with fleet_page(tmp_path, browser, webviz_factory) as (relay, web, page, problems):
        r1 = relay.robots["r1"]
        await sign_in(page, web.url, OPERATOR_TOKEN)
        assert r1.ws is not None
        await r1.ws.send(encode_subscription("/r1/goal_pose", codec=relay.codec))
        await page.goto(web.url + "#/robot/r1")
        await wait_js(page, "fleetviz.conn.active.has('/r1/odom')")
        x = [0.0]
        r1.repeat(lambda: [r1.encode(ODOM, "/odom", {
            **odom_values(), "pose": {"pose": pose_values(x[0], 0.0, 0.0)}})])
        path = "fleetviz.views.map.path"
        await wait_js(page, f"{path}.length >= 1")
        for step in (0.5, 1.0, 4.0):  # driving, driving, then a jump of 3 m
            x[0] = step
            await wait_js(page, f"{path}.some(p => p && p.x === {step})")
        assert await page.evaluate(f"{path}.map(p => p && p.x)") == [0.0, 0.5, 1.0, None, 4.0]
        # The 3D scene's trail breaks there too (it drew a line the robot never drove): two
        # segments, 0 -> 0.5 -> 1 m, none to 4 m.
        trail = ("fleetviz.views.scene.entries.get('/r1/odom trail')"
                 ".content.geometry.attributes.position.array")
        xs = await page.evaluate(f"[...{trail}].filter((_, i) => i % 3 === 0)")
        assert xs == [0.0, 0.5, 0.5, 1.0], xs
        # The robot's arrow is sized in CSS px: drawn at 22 canvas px in a ~330 px panel it was
        # a speck at the end of its path (4 solid pixels here; now ~50).
        await page.set_viewport_size({"width": 1100, "height": 800})  # 3 columns: ~340 px
        await wait_js(page, "fleetviz.views.map.lineScale > 1.5")
        robot = colored_pixels(await page.locator("#map-canvas").screenshot(), POSE_RGB)
        assert robot > 30, robot
        await page.set_viewport_size({"width": 1280, "height": 800})

        await page.click("#tool-goal")
        await page.locator("#command-status", has_text="press on the map").wait_for(
            timeout=TIMEOUT_MS)
        assert "active" in (await page.get_attribute("#tool-goal", "class") or "")
        canvas = page.locator("#map-canvas")
        await canvas.scroll_into_view_if_needed()
        box = await canvas.bounding_box()
        cx, cy = box["width"] * 0.25, box["height"] * 0.5  # world (-4, 0) at 40 px/m
        # The map has a scale: 2 m at 40 px/m, its bar 80 of the canvas's 640 px.
        assert await page.text_content("#map-scale .label") == "2 m"
        bar = await page.locator("#map-scale .bar").bounding_box()
        assert abs(bar["width"] - box["width"] * 80 / 640) < 1, (bar, box)
        # Where the goal would go is said in metres while aiming, its heading while dragging.
        await canvas.hover(position={"x": cx, "y": cy})
        await page.locator("#command-status", has_text="Navigation goal at x=").wait_for(
            timeout=TIMEOUT_MS)
        x_m, y_m = aimed(await page.text_content("#command-status"))
        assert abs(x_m + 4.0) < 0.1 and abs(y_m) < 0.1
        await page.mouse.down()
        await canvas.hover(position={"x": cx, "y": cy - 30})
        await page.locator("#command-status", has_text="yaw=90° (odom): release to send").wait_for(
            timeout=TIMEOUT_MS)
        await page.mouse.up()
        goal = relay.codec.decode(await r1.next_frame(GOAL, 10.0))[1]
        assert abs(goal.pose.position.x + 4.0) < 0.1 and abs(goal.pose.position.y) < 0.1
        await page.locator("#command-status", has_text="Sent navigation goal").wait_for(
            timeout=TIMEOUT_MS)
        assert "active" not in (await page.get_attribute("#tool-goal", "class") or "")
        await wait_js(page, "fleetviz.views.map.sent.length === 1")
        assert colored_pixels(await canvas.screenshot(), GOAL_RGB) > 30  # its arrow stays

        # No tool: a drag pans the view (100 CSS px to the left = the view moves right).
        before = await page.evaluate("fleetviz.views.map.center.x")
        await canvas.hover(position={"x": box["width"] * 0.6, "y": box["height"] * 0.5})
        await page.mouse.down()
        await canvas.hover(position={"x": box["width"] * 0.6 - 100, "y": box["height"] * 0.5})
        await page.mouse.up()
        moved_m = await page.evaluate("fleetviz.views.map.center.x") - before
        expect_m = 100 * 640 / box["width"] / 40
        assert abs(moved_m - expect_m) < 0.05, (moved_m, expect_m)
        assert await page.evaluate("fleetviz.views.map.sent.length") == 1  # no goal sent

        # Esc disarms a tool, mid-press too: nothing is sent (the button again was the only way).
        await page.click("#tool-initial")
        await canvas.hover(position={"x": cx, "y": cy})
        await page.mouse.down()
        await page.keyboard.press("Escape")
        await page.mouse.up()
        await page.locator("#command-status", has_text="Initial pose: cancelled.").wait_for(
            timeout=TIMEOUT_MS)
        assert await page.evaluate("fleetviz.views.map.tool") is None
        assert "active" not in (await page.get_attribute("#tool-initial", "class") or "")
        assert await page.evaluate("fleetviz.views.map.sent.length") == 1
        assert not problems, problems


def aimed(status: str) -> tuple[float, float]:
    """(x, y) in metres from the map's 'Navigation goal at x=... m y=... m' line."""
    match = re.search(r"x=(-?[0-9.]+) m y=(-?[0-9.]+) m", status)
    assert match, status
    return float(match.group(1)), float(match.group(2))


async def test_old_data_is_said_without_moving_the_page(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    # Everything shown at once on a slow machine put the page 3.7 s behind the robots, and
    # only the link health table (at the bottom) said so.
    async with fleet_page(tmp_path, browser, webviz_factory) as (relay, web, page, problems):
        r1 = relay.robots["r1"]
        await open_robot_page(page, web.url, ["/r1/scan"])
        age_s = [3.0]
        seq = [0]

        def late_scan() -> list[bytes]:
            seq[0] += 1
            msg = make(relay.codec.registry, SCAN, scan_of(3.0))
            return [relay.codec.encode(msg, SCAN, "/r1/scan", seq=seq[0],
                                       publish_time_ns=time.time_ns() - int(age_s[0] * 1e9))]

        r1.repeat(late_scan, period_s=0.05)
        map_box = await page.locator("#map-canvas").bounding_box()
        await page.locator("#behind-note", has_text=(
            "r1's data here is 3.0 s old (the link or this browser cannot keep up, or the "
            "robot's clock is off)")).wait_for(
            timeout=TIMEOUT_MS)
        assert await page.locator("#map-canvas").bounding_box() == map_box  # nothing moved
        age_s[0] = 0.0  # caught up: the note goes once the 5 s window has only new samples
        await page.locator("#behind-note").wait_for(state="hidden", timeout=TIMEOUT_MS)
        assert not problems, problems


async def test_a_robot_that_stops_sending_looks_stale_and_offline(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    # A robot whose client stopped sending (frozen, its link dead) left every panel looking
    # live: the last scan, the odometry's 0.40 m/s, nothing saying how old; the robot page
    # never said the robot had gone offline (only the overview did).
    async with fleet_page(tmp_path, browser, webviz_factory) as (relay, web, page, problems):
        r1 = relay.robots["r1"]
        await open_robot_page(page, web.url, ["/r1/scan", "/r1/odom"])
        r1.repeat(lambda: [r1.encode(SCAN, "/scan", scan_of(3.0)),
                           r1.encode(ODOM, "/odom", odom_values())])
        sending = r1.tasks[-1]
        await page.locator("#odom-text", has_text="0.40 m/s").wait_for(timeout=TIMEOUT_MS)
        await wait_js(page, "document.querySelector('#scan-canvas').dataset.beams")
        await page.locator("#robot-state", has_text="online").wait_for(timeout=TIMEOUT_MS)
        heights = {p: (await page.locator(f"#panel-{p}").bounding_box())["height"]
                   for p in ("scan", "odom", "map")}
        pause = await page.locator("#pause").bounding_box()
        assert await page.locator(".panel.stale").count() == 0
        assert await page.locator("#panel-scan h3 .age").text_content() == ""

        sending.cancel()  # still connected, sending nothing
        for p in ("scan", "odom", "map", "scene"):
            await page.locator(f"#panel-{p}.stale h3 .age", has_text="no data for"
                               ).wait_for(timeout=TIMEOUT_MS)
        assert await page.is_visible("#panel-scan.stale h3 .age")
        opacity = "sel => getComputedStyle(document.querySelector(sel)).opacity"
        assert float(await page.evaluate(opacity, "#panel-scan canvas")) < 1
        assert float(await page.evaluate(opacity, "#odom-text")) < 1
        assert await page.text_content("#robot-state") == "online"  # connected, just quiet
        for p, h in heights.items():  # the label sits in the title's line: nothing moved
            assert (await page.locator(f"#panel-{p}").bounding_box())["height"] == h, p
        # Panels that never drew are not called stale: there is nothing old to show.
        assert await page.locator("#panel-gps.stale, #panel-camera.stale").count() == 0

        r1.repeat(lambda: [r1.encode(SCAN, "/scan", scan_of(3.0)),
                           r1.encode(ODOM, "/odom", odom_values())])
        await page.locator(".panel.stale").first.wait_for(state="detached", timeout=TIMEOUT_MS)
        assert await page.locator("#panel-scan h3 .age").text_content() == ""

        await r1.stop()  # gone: the relay's registry says offline, and so does the page
        await page.locator("#robot-state", has_text="offline, last seen").wait_for(
            timeout=TIMEOUT_MS)
        assert await page.get_attribute("#robot-state", "data-state") == "offline"
        # The state is said after Pause: the button does not move as its words change.
        assert await page.locator("#pause").bounding_box() == pause
        assert not problems, problems
