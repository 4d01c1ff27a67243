"""The robot's 3D scene in a real headless Chromium: messages placed through the robot's
TF tree (real relay, a robot that is a real WebSocket client sending tf2_msgs/TFMessage)."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fleetctl.client.viewercloud import VIEWER_CLOUD_TYPE
from fleetctl.client.viewercloud import encode as encode_viewer
from fleetctl.wire.compression import CompressionCodec, compress
from tests.webviz.conftest import webviz_server
from tests.webviz.msgs import make
from tests.webviz.pixels import colored_pixels
from tests.webviz.samples import cloud_values, header, pose_values
from tests.webviz.scripted import (
    TF_TYPE,
    Transform,
    VideoFeed,
    grid_values,
    matrix_of,
    scan_in,
    scripted_fleet,
    tf_values,
)
from tests.webviz.test_browser import (
    SCREENSHOTS,
    TIMEOUT_MS,
    open_robot_page,
    wait_js,
    watch_errors,
)
from tests.webviz.video import encode

pytestmark = pytest.mark.browser

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
SCAN_RGB = (255, 157, 46)  # #ff9d2e, the scene's scan colour
# map -> odom turned 90 degrees, the robot 1 m along odom's x, the scanner mounted
# backwards 0.2 m ahead and 0.3 m up: every step of the chain changes the answer.
DYNAMIC: list[Transform] = [("map", "odom", (10.0, 0.0, 0.0), math.pi / 2),
                            ("odom", "base_link", (1.0, 0.0, 0.0), 0.0)]
STATIC: list[Transform] = [("base_link", "base_scan", (0.2, 0.0, 0.3), math.pi)]


def placement_js(key: str) -> str:
    return f"fleetviz.views.scene.placement('{key}')"


async def test_scan_is_drawn_in_the_map_frame_through_tf(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    async with scripted_fleet(tmp_path) as relay:
        r1 = relay.robots["r1"]
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport={"width": 1400, "height": 1100})
        problems = watch_errors(page)
        await open_robot_page(page, web.url, ["/r1/tf", "/r1/tf_static", "/r1/scan"])
        r1.repeat(lambda: [r1.encode(TF_TYPE, "/tf", tf_values(DYNAMIC)),
                           r1.encode(TF_TYPE, "/tf_static", tf_values(STATIC)),
                           r1.encode(SCAN_TYPE, "/scan", scan_in("base_scan"))])
        await wait_js(page, f"{placement_js('/r1/scan')}?.visible === true")
        placed = await page.evaluate(placement_js("/r1/scan"))
        assert placed["fixed"] == "map" and placed["frame"] == "base_scan"
        assert placed["points"] == 360
        # three.js keeps matrices column-major: transpose to compare with numpy's rows.
        drawn = np.array(placed["matrixWorld"]).reshape(4, 4).T
        np.testing.assert_allclose(drawn, matrix_of(DYNAMIC + STATIC), atol=1e-6)
        # The first beam (angle -pi, 2.0 - 0 m) of the backwards scanner points forward:
        # base_link x = 0.2 + 2.0, i.e. odom (3.2, 0), i.e. map (10, 3.2).
        beam = drawn @ np.array([-2.0, 0.0, 0.0, 1.0])
        np.testing.assert_allclose(beam[:3], [10.0, 3.2, 0.3], atol=1e-3)
        # Really drawn, in the scan's colour; and the page says which frame it draws in.
        await page.locator("#scene-fixed", has_text="Fixed frame: map").wait_for(timeout=TIMEOUT_MS)
        shot = await page.locator("#scene-canvas").screenshot()
        assert colored_pixels(shot, SCAN_RGB) > 100
        tree = page.locator("#tf-tree li")
        await tree.nth(3).wait_for(timeout=TIMEOUT_MS)
        assert [await li.get_attribute("data-frame") for li in await tree.all()] == [
            "map", "odom", "base_link", "base_scan"]
        assert "static" in (await tree.nth(3).text_content() or "")
        assert await page.is_hidden("#scene-problems")
        # Axes per frame: one per frame, placed by the same tree.
        await page.check("#scene-axes")
        await wait_js(page, "[...fleetviz.views.scene.axes.values()].filter(a => a.visible)"
                            ".length === 4")
        assert not problems, problems


async def test_a_broken_tf_chain_is_said_and_the_scan_is_not_drawn(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    async with scripted_fleet(tmp_path) as relay:
        r1 = relay.robots["r1"]
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport={"width": 1400, "height": 1100})
        problems = watch_errors(page)
        await open_robot_page(page, web.url, ["/r1/tf", "/r1/tf_static", "/r1/scan"])
        dynamic = DYNAMIC[:1]  # odom -> base_link missing: base_link hangs in the air
        r1.repeat(lambda: [r1.encode(TF_TYPE, "/tf", tf_values(dynamic)),
                           r1.encode(TF_TYPE, "/tf_static", tf_values(STATIC)),
                           r1.encode(SCAN_TYPE, "/scan", scan_in("base_scan"))])
        said = "/r1/scan: frame base_scan not connected to map (base_link has no parent)"
        await page.locator("#scene-problems li", has_text=said).wait_for(timeout=TIMEOUT_MS)
        placed = await page.evaluate(placement_js("/r1/scan"))
        assert placed["visible"] is False
        assert colored_pixels(await page.locator("#scene-canvas").screenshot(), SCAN_RGB) == 0
        # The missing link arrives: the scan is placed and the sentence goes.
        dynamic.append(DYNAMIC[1])
        await wait_js(page, f"{placement_js('/r1/scan')}.visible === true")
        await page.locator("#scene-problems").wait_for(state="hidden", timeout=TIMEOUT_MS)
        assert colored_pixels(await page.locator("#scene-canvas").screenshot(), SCAN_RGB) > 100
        assert not problems, problems


ROOM_HALF_M = 4.9  # inner face of the walls of grid_values(size=200, resolution_m=0.05)


def robot_pose(t: float) -> tuple[float, float, float]:
    """The robot drives a circle of 2 m around the room's centre (x, y in m, yaw in rad)."""
    a = 0.3 * t
    return 2.0 * math.cos(a), 2.0 * math.sin(a), a + math.pi / 2


def room_scan(x: float, y: float, yaw: float, beams: int = 360) -> dict[str, Any]:
    """What a scanner at (x, y, yaw) in the map sees of the square room's walls."""
    values = scan_in("base_scan", beams)
    angles = values["angle_min"] + np.arange(beams) * values["angle_increment"] + yaw
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (ROOM_HALF_M - x) / c, (-ROOM_HALF_M - x) / c)
        ty = np.where(s > 0, (ROOM_HALF_M - y) / s, (-ROOM_HALF_M - y) / s)
    values["ranges"] = np.minimum(np.abs(tx), np.abs(ty)).astype(np.float32)
    return values


def pillar_cloud(x: float, y: float, yaw: float) -> dict[str, Any]:
    """Points on two pillars in the room, in the frame of a lidar on the robot."""
    rng = np.random.default_rng(7)
    pts = []
    for px, py in ((-2.5, 2.5), (2.5, -2.0)):
        a = rng.uniform(0, 2 * np.pi, 4000)
        pts.append(np.stack([px + 0.3 * np.cos(a), py + 0.3 * np.sin(a),
                             rng.uniform(0, 1.5, 4000)], axis=1))
    world = np.concatenate(pts)
    # map -> lidar (lidar 0.5 m above base_link, which is at (x, y, yaw)).
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = world[:, 0] - x, world[:, 1] - y
    local = np.stack([c * dx + s * dy, -s * dx + c * dy, world[:, 2] - 0.5], axis=1)
    values = cloud_values(len(local))
    values["header"] = header("lidar")
    values["data"] = np.frombuffer(local.astype(np.float32).tobytes(), dtype=np.uint8)
    return values


def room_markers() -> dict[str, Any]:
    base = {"header": header("map"), "ns": "room", "action": 0, "color": {"a": 1.0}}
    return {"markers": [
        {**base, "id": 1, "type": 9, "pose": {**pose_values(0.0, 4.3, 0.0), "position": {
            "x": 0.0, "y": 4.3, "z": 0.8}}, "text": "dock",
         "scale": {"z": 0.5}, "color": {"r": 1.0, "g": 0.8, "b": 0.2, "a": 1.0}},
        {**base, "id": 2, "type": 1, "pose": pose_values(0.0, 4.3, 0.0),
         "scale": {"x": 1.0, "y": 0.4, "z": 0.4}, "color": {"g": 0.8, "b": 0.4, "a": 1.0}},
        {**base, "id": 3, "type": 3, "pose": pose_values(-3.5, -3.5, 0.0),
         "scale": {"x": 0.6, "y": 0.6, "z": 1.0},
         "color": {"r": 0.9, "g": 0.3, "b": 0.3, "a": 0.8}},
    ]}


async def test_scene_with_tf_map_scan_cloud_markers_and_video(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    """Everything at once, as an operator sees a moving robot (and the docs' screenshot)."""
    units = encode("h264", 90, width=480, height=360, keyframe_every=30, source="photo")
    async with scripted_fleet(tmp_path) as relay:
        r1 = relay.robots["r1"]
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport={"width": 1500, "height": 1000})
        problems = watch_errors(page)
        await open_robot_page(page, web.url, ["/r1/tf", "/r1/scan", "/r1/points/viewer",
                                              "/r1/camera/image_raw", "/r1/map"])
        for panel in ("camera", "scan", "cloud", "map", "odom", "gps"):
            await page.uncheck(f"#show-{panel}")
        t0 = time.monotonic()
        static = [("base_link", "base_scan", (0.2, 0.0, 0.3), 0.0),
                  ("base_link", "lidar", (0.0, 0.0, 0.5), 0.0),
                  ("base_link", "camera", (0.3, 0.0, 0.4), 0.0)]

        def frames() -> list[bytes]:
            x, y, yaw = robot_pose(time.monotonic() - t0)
            dyn = [("map", "odom", (0.0, 0.0, 0.0), 0.0), ("odom", "base_link", (x, y, 0.0), yaw)]
            cloud = make(relay.codec.registry, "sensor_msgs/msg/PointCloud2",
                         pillar_cloud(x, y, yaw))
            viewer = relay.codec.encode(encode_viewer(cloud, 0.02), VIEWER_CLOUD_TYPE,
                                        "/r1/points/viewer")
            odom = {"header": header("odom"), "child_frame_id": "base_link",
                    "pose": {"pose": pose_values(x, y, yaw)}}
            return [
                r1.encode(TF_TYPE, "/tf", tf_values(dyn)),
                r1.encode(TF_TYPE, "/tf_static", tf_values(static)),
                r1.encode(SCAN_TYPE, "/scan", room_scan(x, y, yaw)),
                r1.encode("nav_msgs/msg/Odometry", "/odom", odom),
                r1.encode("nav_msgs/msg/OccupancyGrid", "/map",
                          grid_values(size=200, resolution_m=0.05)),
                r1.encode("visualization_msgs/msg/MarkerArray", "/markers", room_markers()),
                compress(viewer, codec=CompressionCodec.DEFLATE, topic="/r1/points/viewer",
                         no_drop=False, frame_codec=relay.codec),
            ]

        r1.repeat(frames, 0.2)
        VideoFeed(r1, "/camera/image_raw", units, "h264").run()
        keys = ["/r1/scan", "/r1/map", "/r1/points/viewer", "/r1/odom", "/r1/odom trail",
                "/r1/markers room/1", "/r1/markers room/3"]
        await wait_js(page, " && ".join(f"{placement_js(k)}?.visible === true" for k in keys))
        # Shown frames prove the camera plays inside the scene; how many depends on the
        # host: with the 3D scene rendering in software on 2 cores under a parallel build,
        # Chromium showed ~3 frames/s of the 30 (the rest skipped as "behind"); before the
        # decoder was kept through "behind" (views/video.js) it was 9 in 36 s, which is how
        # this wait failed under CI load. The decode rate itself is test_video_browser's.
        await wait_js(page, "(fleetviz.views.video.stats['/r1/camera/image_raw']?.shown ?? 0)"
                            " >= 5")
        cloud = await page.evaluate(placement_js("/r1/points/viewer"))
        assert cloud["points"] > 1000 and cloud["frame"] == "lidar"
        await page.check("#scene-axes")
        await wait_js(page, "fleetviz.views.scene.axes.size === 6")
        shot = await page.locator("#scene-canvas").screenshot()
        assert colored_pixels(shot, SCAN_RGB) > 100
        assert await page.is_hidden("#scene-problems")
        if SCREENSHOTS:
            await wait_js(page, "document.querySelector('#video-status').textContent"
                                ".includes('decoded')")
            await page.screenshot(path=str(Path(SCREENSHOTS) / "scene.png"), full_page=True)
        assert not problems, problems


# Counts the shader programs the page links (every WebGL context, from the first script on).
COUNT_LINKS = """(() => {
  window.__programLinks = 0;
  for (const C of [WebGLRenderingContext, WebGL2RenderingContext]) {
    const link = C.prototype.linkProgram;
    C.prototype.linkProgram = function (p) { window.__programLinks++; return link.call(this, p); };
  }
})();"""


async def test_messages_replacing_each_other_link_no_new_shader_programs(
    tmp_path: Path, browser: Any, webviz_factory: list[Any]
) -> None:
    """Each scan, cloud and odometry replaces the one before it in the scene. three.js
    deletes a program with its last material, so disposing the old object before the new
    one was drawn compiled and linked the same program again for every message (12.5 links
    a second for one simulated robot, a synchronous wait on the GPU process each)."""
    async with scripted_fleet(tmp_path) as relay:
        r1 = relay.robots["r1"]
        web = webviz_server(relay.url).start()
        webviz_factory.append(web)
        page = await browser.new_page(viewport={"width": 1400, "height": 1100})
        await page.add_init_script(COUNT_LINKS)
        problems = watch_errors(page)
        await open_robot_page(page, web.url, ["/r1/tf", "/r1/scan", "/r1/points", "/r1/odom"])
        cloud = {**cloud_values(500), "header": header("odom")}
        odom = {"header": header("odom"), "child_frame_id": "base_link",
                "pose": {"pose": pose_values(1.0, 2.0, 0.0)}}
        r1.repeat(lambda: [r1.encode(TF_TYPE, "/tf", tf_values(DYNAMIC[:1])),
                           r1.encode(SCAN_TYPE, "/scan", scan_in("odom")),
                           r1.encode("sensor_msgs/msg/PointCloud2", "/points", cloud),
                           r1.encode("nav_msgs/msg/Odometry", "/odom", odom)],
                  period_s=0.05)
        for key in ("/r1/scan", "/r1/points", "/r1/odom"):
            await wait_js(page, f"{placement_js(key)}?.visible === true")
        scene = "document.querySelector('#scene-canvas').dataset"
        # Warm-up: a kind of object drawn the first time links its program once (a CI run
        # saw 2 such links inside the window when it opened as the third object showed).
        # Wait for 10 draws in a row without a link; before the fix every message linked,
        # so that never came.
        await wait_js(page, f"""(() => {{
            const d = Number({scene}.draws), l = window.__programLinks;
            if (window.__quiet?.links !== l) window.__quiet = {{links: l, draws: d}};
            return d >= window.__quiet.draws + 10;
        }})()""")
        draws = await page.evaluate(f"Number({scene}.draws)")
        linked = await page.evaluate("window.__programLinks")
        await wait_js(page, f"fleetviz.views.scene.stats.messages > 0 && Number({scene}.draws)"
                            f" >= {draws + 20}")
        assert await page.evaluate("window.__programLinks") == linked
        assert not problems, problems
