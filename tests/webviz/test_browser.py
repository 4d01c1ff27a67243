"""The page in a real headless Chromium against a real relay and real WebSocket robots."""

from __future__ import annotations

import asyncio
import math
import os
import time
from pathlib import Path
from typing import Any

import pytest

from fleetctl.server.app import RelayServer
from fleetctl.server.authmap import load_auth_map
from fleetctl.server.config import ServerConfig, WebConfig
from fleetctl.wire.codec import Codec
from fleetctl.wire.metadata import read_metadata
from fleetctl.wire.registry import TypeRegistry
from tests.server.certs import self_signed
from tests.webviz.conftest import webviz_server
from tests.webviz.fleet import (
    OPERATOR_TOKEN,
    R1_VIEWER_TOKEN,
    VIEWER_TOKEN,
    WsRobot,
    running_fleet,
    write_auth_map,
)
from tests.webviz.pixels import drawn_fraction_within, drawn_pixels

pytestmark = pytest.mark.browser

PANEL_BG = (16, 20, 24)  # #101418, the sensor canvases' background
MAP_BG = (27, 33, 39)  # #1b2127, the map canvas background
TIMEOUT_MS = 15_000
SCREENSHOTS = os.environ.get("FLEETCTL_WEBVIZ_SCREENSHOTS")  # e.g. docs/screenshots


async def wait_js(page: Any, expr: str) -> None:
    """Wait (bounded) until the JS expression is true in the page."""
    await page.wait_for_function(expr, timeout=TIMEOUT_MS)


async def sign_in(page: Any, url: str, token: str) -> None:
    await page.goto(url)
    await page.fill("#token", token)
    await page.click("#signin-button")
    await wait_js(page, "document.querySelector('#conn-state').textContent === 'open'")


async def open_robot_page(page: Any, url: str, topics: list[str], robot: str = "r1") -> None:
    """Sign in as an operator, open *robot*'s page and wait until the server confirmed
    the page's subscriptions to *topics*."""
    await sign_in(page, url, OPERATOR_TOKEN)
    await page.goto(url + f"#/robot/{robot}")
    await wait_js(page, " && ".join(f"fleetviz.conn.active.has('{t}')" for t in topics))


async def next_frame_of(robot: WsRobot, type_name: str, timeout_s: float) -> bytes:
    deadline = time.monotonic() + timeout_s
    while True:
        left = max(0.01, deadline - time.monotonic())
        frame = await asyncio.wait_for(robot.received.get(), left)
        if read_metadata(frame).type == type_name:
            return frame


async def pixels(page: Any, selector: str, background: tuple[int, int, int] = PANEL_BG) -> int:
    return drawn_pixels(await page.locator(selector).screenshot(), background)


def watch_errors(page: Any) -> list[str]:
    problems: list[str] = []
    page.on("pageerror", lambda e: problems.append(f"pageerror: {e}"))

    def console(m: Any) -> None:
        if m.type == "error":
            problems.append(f"console: {m.text}")

    def response(r: Any) -> None:
        if r.status >= 400:
            problems.append(f"HTTP {r.status} {r.url}")

    page.on("console", console)
    page.on("response", response)
    return problems


async def check_overview(page: Any) -> None:
    for name in ("r1", "r2"):
        row = page.locator(f'#robots tr[data-robot="{name}"]')
        await row.locator("td.state", has_text="online").wait_for(timeout=TIMEOUT_MS)
        await row.locator("td", has_text="patrolling").wait_for(timeout=TIMEOUT_MS)
    assert "signed in as operator" in await page.text_content("#identity")
    if SCREENSHOTS:
        await wait_js(page, "document.querySelector('#robots').textContent.includes('msg/s')")
        await page.screenshot(path=str(Path(SCREENSHOTS) / "overview.png"))


async def check_sensor_panels(page: Any, robot: str, *, beams: int,
                              camera_min_fraction: float) -> None:
    """Open *robot*'s page; its camera, scan (*beams* beams) and WebGL cloud are drawn."""
    await page.click(f'#robots a[href="#/robot/{robot}"]')
    await wait_js(
        page,
        "Number(document.querySelector('#camera-canvas').dataset.frames || 0) >= 1"
        f" && Number(document.querySelector('#scan-canvas').dataset.beams || 0) === {beams}"
        " && Number(document.querySelector('#cloud-canvas').dataset.points || 0) > 1000",
    )
    assert await page.get_attribute("#cloud-canvas", "data-mode") == "webgl"
    camera = page.locator("#camera-canvas")
    drawn = await drawn_fraction_within(camera, PANEL_BG, camera_min_fraction)
    assert drawn > camera_min_fraction
    assert await pixels(page, "#scan-canvas") > 300
    assert await pixels(page, "#cloud-canvas") > 300


async def check_robot_views(page: Any) -> None:
    # The gradient covers the whole camera canvas.
    await check_sensor_panels(page, "r1", beams=360, camera_min_fraction=0.9)
    await wait_js(page, "document.querySelector('#odom-text').textContent.includes('0.60 m/s')")
    # Latitude and longitude with their units and names (it was "30.286200, -97.736500"),
    # and a metric scale on the tile-less GPS map (it had no sense of distance at all).
    await page.locator("#gps-text", has_text="lat 30.286200° lon -97.736500° alt 150.0 m, fix"
                       ).wait_for(timeout=TIMEOUT_MS)
    scale = await page.text_content("#gps-map .leaflet-control-scale-line") or ""
    assert scale.endswith((" m", " km")), scale
    # The occupancy grid (8 m square = 320x320 of the 640x480 canvas at 40 px/m) is drawn;
    # r1 sends it deflate-compressed, so Chromium's DecompressionStream inflated it.
    await wait_js(page, "fleetviz.views.map.grid !== null && fleetviz.conn.stats.decompressed >= 1")
    assert await drawn_fraction_within(page.locator("#map-canvas"), MAP_BG, 0.25) > 0.25
    await page.locator("#health tbody tr", has_text="/r1/scan").wait_for(timeout=TIMEOUT_MS)
    assert not await page.is_visible("#command-denied")


# Fills the scene's problem list and its TF tree as a busy robot's would, reads where the
# map is after each, and puts both back (one task: the page's own updates cannot run
# between).
_MAP_BOX_WHILE_LISTS_GROW = """() => {
  const box = () => JSON.stringify(document.querySelector('#map-canvas').getBoundingClientRect());
  const items = (n, text) => Array.from({length: n}, (_, i) =>
    Object.assign(document.createElement('li'), {textContent: `${text} ${i}`}));
  const problems = document.querySelector('#scene-problems');
  const tree = document.querySelector('#tf-tree');
  const saved = [problems.hidden, [...problems.childNodes], [...tree.childNodes]];
  problems.replaceChildren(); problems.hidden = true;
  const before = box();
  problems.replaceChildren(...items(1, 'a problem')); problems.hidden = false;
  const one = box();
  problems.replaceChildren(...items(12, 'a problem'));
  const many = box();
  tree.replaceChildren(...items(120, 'frame'));
  const tall = box();
  problems.hidden = saved[0]; problems.replaceChildren(...saved[1]);
  tree.replaceChildren(...saved[2]);
  return [before, one, many, tall];
}"""


async def check_map_holds_still_while_the_scene_lists_change(page: Any) -> None:
    """The map stays where it is when the scene's problem list appears or grows and when
    its TF tree grows (they are above it): an operator aiming a goal would otherwise
    press on another point of the map."""
    boxes = await page.evaluate(_MAP_BOX_WHILE_LISTS_GROW)
    assert len(set(boxes)) == 1, boxes


async def wait_map_still(page: Any) -> None:
    """Until the map canvas has stayed in place for 0.5 s (bounded: 15 s)."""
    await page.wait_for_function(
        "() => { const r = document.querySelector('#map-canvas').getBoundingClientRect();"
        " const k = [r.x, r.y, r.width, r.height].join(); const w = (window.__mapBox ??="
        " {k: '', n: 0}); if (w.k === k) w.n++; else { w.k = k; w.n = 0; }"
        " return w.n >= 5; }", polling=100, timeout=15_000)


# The canvas's box and the scroll at every animation frame until the press: a line that
# wrapped and unwrapped in between would move the canvas and back, unseen by two reads.
_WATCH_BOX = """el => {
  const rows = (window.__pressBoxes = []);
  // What above the canvas changed height when it moved (the boxes alone do not say).
  const parts = () => new Map([...document.querySelectorAll(
    "header, #banner, #robot > *, .panel, .panel > *, .panel h3 > *")].map((e, i) =>
    [`${i}:${e.id || e.tagName + "." + e.className}`,
     e.getBoundingClientRect().height.toFixed(1)]));
  const first = parts();
  window.__pressChanged = [];
  const step = () => {
    if (window.__pressBoxes !== rows) return;
    const r = el.getBoundingClientRect();
    const box = [r.x, r.y, r.width, r.height, scrollY].map((v) => v.toFixed(1)).join();
    if (rows.length && box !== rows[rows.length - 1]) {
      for (const [k, h] of parts()) {
        if (first.get(k) !== h) window.__pressChanged.push(`${k} ${first.get(k)} -> ${h}`);
      }
    }
    rows.push(box);
    requestAnimationFrame(step);
  };
  step();
}"""
_BOXES_SEEN = "(() => { const s = [...new Set(window.__pressBoxes)]; window.__pressBoxes = null;" \
              " return [s, window.__pressChanged]; })()"


async def press_where_aimed(page: Any, canvas: Any, x: float, y: float) -> None:
    """Point at (*x*, *y*) of *canvas* and press the mouse button there; the canvas must
    not move between the aim and the press.

    The press lands where the pointer is on the screen: a line of text wrapping in a panel
    above the map in that instant moved it 20 px (a CI run's second demo goal arrived at
    y = 2.5 for 2.0). This helper used to cancel such a press and aim again; the page now
    keeps every live text from moving the map (css/app.css, test_layout_browser.py), so a
    move is a failure again, with the boxes seen frame by frame."""
    before = await canvas.bounding_box()
    await canvas.evaluate(_WATCH_BOX)
    await canvas.hover(position={"x": x, "y": y})
    await page.mouse.down()
    after = await canvas.bounding_box()
    seen, changed = await page.evaluate(_BOXES_SEEN)
    assert after == before and len(seen) <= 1, (
        f"the canvas moved between the aim and the press: {before} -> {after}; "
        f"x, y, width, height, scrollY seen: {seen}; heights that changed: {changed}")


async def aim_goal_tool(page: Any, fx: float, fy: float) -> dict[str, float]:
    """Arm the goal tool and press at (*fx*, *fy*) of the map canvas (fractions of its
    size), once it is in view and has held still; the canvas's box. The press must reach
    the map at the world point aimed at (the view's centre and scale are said if not)."""
    canvas = page.locator("#map-canvas")
    await page.click("#tool-goal")
    await canvas.scroll_into_view_if_needed()
    await wait_map_still(page)
    box: dict[str, float] = await canvas.bounding_box()
    await press_where_aimed(page, canvas, box["width"] * fx, box["height"] * fy)
    where = await page.evaluate(
        "([fx, fy]) => { const m = fleetviz.views.map;"
        " const want = m.toWorld(fx * m.canvas.width, fy * m.canvas.height);"
        " return {want, got: m.drag?.start ?? null, tool: m.tool, center: m.center,"
        " scale: m.scale, rect: m.canvas.getBoundingClientRect().toJSON()}; }", [fx, fy])
    got, want = where["got"], where["want"]
    off = got is None or max(abs(got["x"] - want["x"]), abs(got["y"] - want["y"])) >= 0.05
    assert not off, f"the press reached the map elsewhere: {where}, box {box}"
    return box


async def drag_goal(page: Any) -> None:
    """Press at x=+4 m, y=0 (map centred on the origin, 40 px/m, 640 px wide), drag up.

    First the map must have stayed in place for 0.5 s: a panel or health row appearing
    above it while the mouse moves would shift the goal (a CI run got y = -1.3 m). Each
    pointer position is then taken relative to the canvas where it is at that moment
    (``hover`` scrolls it into view and checks the point reaches the canvas), not from
    a box read before: a press below the viewport or on a panel that moved over the
    map reaches nothing (a CI run sent no goal at all); and the canvas must not move
    during the press (:func:`press_where_aimed`)."""
    box = await aim_goal_tool(page, 0.75, 0.5)
    canvas = page.locator("#map-canvas")
    x, y = box["width"] * 0.75, box["height"] * 0.5
    for step in range(1, 6):
        await canvas.hover(position={"x": x, "y": y - box["height"] * 0.04 * step})
    await page.mouse.up()
    status = "document.querySelector('#command-status').textContent"
    try:
        await wait_js(page, f"{status}.startsWith('Sent') || {status}.startsWith('Not sent')")
    except Exception as err:
        shown = await page.evaluate(f"[{status}, fleetviz.views.map.tool]")
        raise AssertionError(f"the drag sent nothing: status, tool = {shown}") from err


async def check_topic_selection_and_pause(page: Any) -> None:
    cam = "/r1/camera/image/compressed"
    await wait_js(page, f"fleetviz.conn.active.has('{cam}')")
    await page.uncheck("#show-camera")
    await wait_js(page, f"!fleetviz.conn.active.has('{cam}')")
    assert await page.is_hidden("#panel-camera")
    # Unsubscribed: camera frames stop while scans keep coming.
    shown = int(await page.get_attribute("#camera-canvas", "data-frames") or 0)
    scans = "fleetviz.conn.health.topics.get('/r1/scan').received"
    base = await page.evaluate(scans)
    await wait_js(page, f"{scans} >= {base} + 10")
    assert int(await page.get_attribute("#camera-canvas", "data-frames") or 0) <= shown + 1
    await page.click("#pause")
    await wait_js(page, "!fleetviz.conn.active.has('/r1/scan')")
    assert await page.is_visible("#paused-note")
    await page.click("#pause")
    await wait_js(page, "fleetviz.conn.active.has('/r1/scan')")
    await page.check("#show-camera")
    await wait_js(page, f"fleetviz.conn.active.has('{cam}')")


async def test_operator_sees_fleet_and_robot_and_sends_a_goal(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    async with running_fleet(tmp_path) as fleet:
        web = webviz_server(fleet.url).start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport={"width": 1400, "height": 1100})
        problems = watch_errors(page)
        await sign_in(page, web.url, OPERATOR_TOKEN)
        await check_overview(page)
        await check_robot_views(page)
        await check_map_holds_still_while_the_scene_lists_change(page)

        await drag_goal(page)
        frame = await next_frame_of(fleet.robots[0], "geometry_msgs/msg/PoseStamped", 10)
        meta, goal = fleet.codec.decode(frame)
        assert meta.topic == "/r1/goal_pose"
        assert goal.pose.position.x == pytest.approx(4.0, abs=0.1)
        assert goal.pose.position.y == pytest.approx(0.0, abs=0.1)
        yaw = 2 * math.atan2(goal.pose.orientation.z, goal.pose.orientation.w)
        assert yaw == pytest.approx(math.pi / 2, abs=0.05)
        assert goal.header.frame_id == "odom"  # the frame of the robot's pose source
        await wait_js(
            page,
            "document.querySelector('#command-status').textContent.startsWith('Sent navigation')",
        )
        if SCREENSHOTS:
            await page.screenshot(path=str(Path(SCREENSHOTS) / "robot.png"), full_page=True)
        await check_topic_selection_and_pause(page)
        assert not problems, problems


async def check_typed_goal_refuses_bad_input(page: Any) -> None:
    """Keyboard only: the tool's button armed by Enter focuses the form's x; a word there
    is refused in words, naming the field, and nothing is sent."""
    await page.focus("#tool-goal")
    await page.keyboard.press("Enter")
    await wait_js(page, "document.activeElement.id === 'pose-x'")
    assert await page.is_visible("#pose-form")
    await page.keyboard.type("abc")  # replaces the prefilled x (selected)
    await page.keyboard.press("Enter")
    error = page.locator("#pose-error")
    await error.wait_for(state="visible", timeout=TIMEOUT_MS)
    assert (await error.text_content() or "").startswith('Not sent: x: "abc" is not a number')
    assert await page.get_attribute("#pose-x", "aria-invalid") == "true"
    assert await page.evaluate("fleetviz.views.map.tool") == "goal"  # still armed
    if SCREENSHOTS:
        path = Path(SCREENSHOTS) / "pose-form-error.png"
        await page.locator("#panel-map").screenshot(path=str(path))


async def check_form_screenshots(page: Any) -> None:
    """The form as it looks at 1024 and 1440 px (FLEETCTL_WEBVIZ_SCREENSHOTS)."""
    if not SCREENSHOTS:
        return
    for width in (1024, 1440):
        await page.set_viewport_size({"width": width, "height": 900})
        path = Path(SCREENSHOTS) / f"pose-form-{width}.png"
        await page.locator("#panel-map").screenshot(path=str(path))


async def type_pose(page: Any, x: str, y: str, yaw: str) -> None:
    for field, text in (("#pose-x", x), ("#pose-y", y), ("#pose-yaw", yaw)):
        await page.fill(field, text)


async def test_operator_types_a_goal_and_keys_an_initial_pose(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    # Beside the dragged goal above: the same message, typed (a dock at x=12.5, y=-3.0,
    # yaw 180°) or keyed on the focused map, without a mouse.
    async with running_fleet(tmp_path, ("r1",)) as fleet:
        web = webviz_server(fleet.url).start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport={"width": 1024, "height": 900})
        problems = watch_errors(page)
        await open_robot_page(page, web.url, ["/r1/odom"])
        await wait_js(page, "fleetviz.views.map.pose !== null")
        await check_typed_goal_refuses_bad_input(page)
        await type_pose(page, "12.5", "-3.0", "180")
        await check_form_screenshots(page)
        await page.press("#pose-yaw", "Enter")
        meta, goal = fleet.codec.decode(
            await next_frame_of(fleet.robots[0], "geometry_msgs/msg/PoseStamped", 10))
        assert meta.topic == "/r1/goal_pose"
        assert (goal.pose.position.x, goal.pose.position.y) == (12.5, -3.0)
        assert 2 * math.atan2(goal.pose.orientation.z, goal.pose.orientation.w) == \
            pytest.approx(math.pi)
        assert goal.header.frame_id == "odom"  # the drag's frame: the robot's pose source
        assert abs(goal.header.stamp.sec - time.time()) < 60
        await page.locator("#command-status", has_text="Sent navigation goal x=12.50 m "
                           "y=-3.00 m yaw=180° to /r1/goal_pose").wait_for(timeout=TIMEOUT_MS)
        assert await page.is_hidden("#pose-form")
        assert await page.evaluate("document.activeElement.id") == "tool-goal"

        # The initial pose, keyed on the focused map: Shift+Right 1 m, Up 0.1 m, Shift+Q 45°.
        await page.click("#tool-initial")
        await type_pose(page, "1", "2", "0")
        await page.focus("#map-canvas")
        scrolled = await page.evaluate("window.scrollY")  # focus scrolls the map into view
        for key in ("Shift+ArrowRight", "ArrowUp", "Shift+Q"):
            await page.keyboard.press(key)
        assert [await page.input_value(f) for f in ("#pose-x", "#pose-y", "#pose-yaw")] == \
            ["2.00", "2.10", "45.0"]
        # The arrows moved the pose, not the page.
        assert await page.evaluate("window.scrollY") == scrolled
        await page.keyboard.press("Enter")
        meta, initial = fleet.codec.decode(await next_frame_of(
            fleet.robots[0], "geometry_msgs/msg/PoseWithCovarianceStamped", 10))
        assert meta.topic == "/r1/initialpose"
        assert initial.pose.pose.position.x == pytest.approx(2.0)
        assert initial.pose.pose.position.y == pytest.approx(2.1)
        orientation = initial.pose.pose.orientation
        assert 2 * math.atan2(orientation.z, orientation.w) == pytest.approx(math.pi / 4)
        assert initial.pose.covariance[0] == 0.25 and initial.header.frame_id == "odom"

        # Armed again, the form starts at the last goal sent; Esc cancels, nothing sent.
        await page.click("#tool-goal")
        assert [await page.input_value(f) for f in ("#pose-x", "#pose-y", "#pose-yaw")] == \
            ["12.50", "-3.00", "180.0"]
        await page.keyboard.press("Escape")
        await page.locator("#command-status", has_text="Navigation goal: cancelled."
                           ).wait_for(timeout=TIMEOUT_MS)
        assert await page.is_hidden("#pose-form")
        assert not problems, problems


async def test_a_zstd_topic_is_explained_in_its_panel(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    async with running_fleet(tmp_path, ("r1", "r2")) as fleet:  # r2 sends its map with zstd
        web = webviz_server(fleet.url).start()
        webviz_factory.append(web)
        page = await browser.new_page()
        problems = watch_errors(page)
        await sign_in(page, web.url, OPERATOR_TOKEN)
        await page.goto(web.url + "#/robot/r2")
        said = "/r2/map is compressed with zstd, which browsers cannot decode"
        note = page.locator("#panel-map .panel-note", has_text=said)
        await note.wait_for(timeout=TIMEOUT_MS)
        assert "set compression: deflate for this topic" in (await note.text_content() or "")
        # The rest of the page is unaffected.
        await wait_js(page, "Number(document.querySelector('#scan-canvas').dataset.beams || 0)"
                            " === 360")
        assert await page.evaluate("fleetviz.conn.stats.decodeErrors") == 0
        assert not problems, problems


async def test_viewer_is_refused_a_command(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    async with running_fleet(tmp_path, ("r1",)) as fleet:
        web = webviz_server(fleet.url).start()
        webviz_factory.append(web)
        page = await browser.new_page()
        await sign_in(page, web.url, VIEWER_TOKEN)
        await page.goto(web.url + "#/robot/r1")
        denied = page.locator("#command-denied")
        await denied.wait_for(state="visible", timeout=TIMEOUT_MS)
        assert "not allowed to send" in await denied.text_content()
        assert await page.is_disabled("#tool-goal") and await page.is_disabled("#tool-initial")
        # Bypass the UI: the server must refuse it too, and the page must say so.
        await page.evaluate(
            """() => fleetviz.conn.sendMessage('geometry_msgs/msg/PoseStamped', '/r1/goal_pose',
            {header: {frame_id: 'map'},
             pose: {position: {x: 1, y: 2, z: 0}, orientation: {w: 1}}})"""
        )
        refusal = page.locator("#errors li", has_text="unauthorized_send on /r1/goal_pose")
        await refusal.wait_for(timeout=TIMEOUT_MS)
        assert "The server refused" in await page.text_content("#command-status")
        types = []
        while not fleet.robots[0].received.empty():
            types.append(read_metadata(fleet.robots[0].received.get_nowait()).type)
        assert "geometry_msgs/msg/PoseStamped" not in types


async def test_a_user_scoped_to_one_robot_is_told_another_is_not_theirs(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    """A user scoped to r1 (fleetctl add-user --robots r1) sees r1 only; r2's page (a link
    someone shared) says the sign-in may not receive it, where it said "not in the fleet's
    robot list" and "Nothing on /r2/scan yet": a broken robot, to whoever read it."""
    async with running_fleet(tmp_path, ("r1", "r2")) as fleet:
        web = webviz_server(fleet.url).start()
        webviz_factory.append(web)
        page = await browser.new_page()
        problems = watch_errors(page)
        await sign_in(page, web.url, R1_VIEWER_TOKEN)
        await page.locator('#robots tr[data-robot="r1"] td.state',
                           has_text="online").wait_for(timeout=TIMEOUT_MS)
        assert await page.locator("#robots tr[data-robot]").count() == 1
        await page.goto(web.url + "#/robot/r2")
        state = page.locator('#robot-state[data-state="denied"]')
        await state.wait_for(timeout=TIMEOUT_MS)
        assert "may not receive" in (await state.text_content() or "")
        scan_note = page.locator("#panel-scan .panel-wait")
        await scan_note.wait_for(state="visible", timeout=TIMEOUT_MS)
        assert await scan_note.text_content() == "Your sign-in may not receive /r2/scan."
        # Its own robot's page is as any viewer's.
        await page.goto(web.url + "#/robot/r1")
        await page.locator('#robot-state[data-state="online"]').wait_for(timeout=TIMEOUT_MS)
        await wait_js(page, "Number(document.querySelector('#scan-canvas').dataset.beams"
                            " || 0) > 0")
        assert not problems, problems


async def test_bad_token_is_refused_with_a_clear_message(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    async with running_fleet(tmp_path, ("r1",)) as fleet:
        web = webviz_server(fleet.url).start()
        webviz_factory.append(web)
        page = await browser.new_page()
        await page.goto(web.url)
        await page.fill("#token", "wrong-token")
        await page.click("#signin-button")
        await page.locator("#banner", has_text="refused the token").wait_for(timeout=TIMEOUT_MS)
        assert await page.is_visible("#signin")
        # Only the form: the empty fleet table and the server messages stood under it.
        assert await page.is_hidden("#main")
        await page.fill("#token", OPERATOR_TOKEN)
        await page.click("#signin-button")
        await page.locator('#robots tr[data-robot="r1"]').wait_for(timeout=TIMEOUT_MS)
        assert await page.is_hidden("#signin") and await page.is_hidden("#banner")
        # The refused token's bad_token is not listed as if something were wrong now.
        assert await page.locator("#errors li").count() == 0


async def test_banner_while_disconnected_then_reconnects(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    auth = load_auth_map(write_auth_map(tmp_path / "auth.yaml", {}))
    config = ServerConfig(
        listen_host="127.0.0.1", listen_port=0, auth_map=tmp_path / "auth.yaml", database=None
    )
    first = RelayServer(config, auth)
    await first.start()
    port = first.port
    url = f"ws://127.0.0.1:{port}/"
    web = webviz_server(url).start()
    webviz_factory.append(web)
    page = await browser.new_page()
    await sign_in(page, web.url, OPERATOR_TOKEN)
    assert await page.is_hidden("#banner")
    await first.stop()
    banner = page.locator("#banner", has_text="Disconnected from the fleet server")
    await banner.wait_for(state="visible", timeout=TIMEOUT_MS)
    second = RelayServer(ServerConfig(**{**config.__dict__, "listen_port": port}), auth)
    await second.start()
    try:
        await wait_js(page, "document.querySelector('#conn-state').textContent === 'open'")
        assert await page.is_hidden("#banner")
    finally:
        await second.stop()


async def test_page_from_the_relays_https_web_listener(tmp_path: Path, browser: Any) -> None:
    """One HTTPS origin: the relay serves the page and its WebSocket (config null -> wss to
    the page's own host and port)."""
    cert, key = self_signed(tmp_path / "tls")
    auth = load_auth_map(write_auth_map(tmp_path / "auth.yaml", {"r1": "127.0.0.2"}))
    config = ServerConfig(
        listen_host="127.0.0.1", listen_port=0, auth_map=tmp_path / "auth.yaml", database=None,
        web=WebConfig(tls_cert=cert, tls_key=key, listen_host="127.0.0.1", listen_port=0),
    )
    async with RelayServer(config, auth) as server:
        robot = WsRobot("r1", "127.0.0.2", server.url, Codec(TypeRegistry.default()))
        await robot.start()
        context = await browser.new_context(ignore_https_errors=True)
        try:
            page = await context.new_page()
            problems = watch_errors(page)
            assert server.web_url is not None
            await sign_in(page, server.web_url, OPERATOR_TOKEN)
            assert await page.text_content("#server-url") == f"wss://127.0.0.1:{server.web_port}/"
            row = page.locator('#robots tr[data-robot="r1"]')
            await row.locator("td.state", has_text="online").wait_for(timeout=TIMEOUT_MS)
            assert "signed in as operator" in await page.text_content("#identity")
            await page.click('#robots a[href="#/robot/r1"]')
            await wait_js(page, "Number(document.querySelector('#scan-canvas').dataset.beams"
                                " || 0) === 360")
            assert not problems, problems
        finally:
            await context.close()
            await robot.stop()
