"""The Point cloud panel (``static/js/views/cloud.js``) in a real headless Chromium with
Debian's three.js: what it holds in WebGL stays the same however many clouds it draws.

A page left open on a wall monitor draws 5 clouds a second for days. Each cloud used to be
a new ``BufferAttribute`` pair, so three.js made two new WebGL buffers per cloud (720 KB
each at 60,000 points) and never deleted the old ones: only the garbage collector taking
their wrappers freed them (docs/webviz.md, "The page left open").
"""

from __future__ import annotations

from typing import Any

import pytest

pytestmark = pytest.mark.browser
CLOUDS = 40
PANEL_BG = (16, 20, 24)  # #101418

# Draws *counts* clouds (of the given point counts, in turn) through the page's own
# CloudView and counts the WebGL buffers its context created, deleted and filled.
DRAW_CLOUDS_JS = """
async (counts) => {
  const { CloudView } = await import("/js/views/cloud.js");
  const canvas = Object.assign(document.createElement("canvas"), { width: 320, height: 240 });
  document.body.append(canvas);
  const view = new CloudView(canvas, "/vendor/");
  await view.ready;
  if (view.mode !== "webgl") return { mode: view.mode, reason: view.reason ?? null };
  const gl = view.renderer.getContext();
  const buffers = { created: 0, deleted: 0, allocated: 0 };
  const { createBuffer, deleteBuffer, bufferData } = gl;
  gl.createBuffer = () => { buffers.created++; return createBuffer.call(gl); };
  gl.deleteBuffer = (b) => { buffers.deleted++; return deleteBuffer.call(gl, b); };
  gl.bufferData = (...args) => { buffers.allocated++; return bufferData.apply(gl, args); };
  const cloud = (n, seed) => {
    const xyz = new Float32Array(4 * n); // x, y, z and a padding float per point
    for (let i = 0; i < n; i++) {
      const a = (i / n) * 2 * Math.PI;
      xyz.set([3 * Math.cos(a + seed), 3 * Math.sin(a + seed), (i % 10) / 5], 4 * i);
    }
    return {
      height: 1, width: n, is_bigendian: false, point_step: 16, row_step: 16 * n,
      fields: ["x", "y", "z"].map((name, i) => ({ name, offset: 4 * i, datatype: 7, count: 1 })),
      data: new Uint8Array(xyz.buffer),
    };
  };
  const live = () => buffers.created - buffers.deleted;
  const drawn = [];
  let afterFirst = null;
  counts.forEach((n, i) => {
    view.update(cloud(n, i));
    view.render();
    drawn.push([Number(canvas.dataset.points), view.geometry.drawRange.count]);
    afterFirst ??= live();
  });
  const px = new Uint8Array(canvas.width * canvas.height * 4);
  gl.readPixels(0, 0, canvas.width, canvas.height, gl.RGBA, gl.UNSIGNED_BYTE, px);
  let lit = 0;
  for (let i = 0; i < px.length; i += 4) {
    if (Math.abs(px[i] - 16) + Math.abs(px[i + 1] - 20) + Math.abs(px[i + 2] - 24) > 60) lit++;
  }
  return { mode: view.mode, afterFirst, live: live(), buffers, drawn, lit };
}
"""


async def test_clouds_drawn_one_after_another_hold_the_same_webgl_buffers(page: Any) -> None:
    # Large and small clouds in turn: a small one after a large one draws only its own.
    counts = [20_000 if i % 2 == 0 else 3_000 for i in range(CLOUDS)]
    out = await page.evaluate(DRAW_CLOUDS_JS, counts)
    assert out["mode"] == "webgl", out
    # Before: 2 more buffers per cloud (80 over 40 clouds), none deleted.
    assert out["live"] == out["afterFirst"], out["buffers"]
    # Each buffer is sized once; the clouds are written into it.
    assert out["buffers"]["allocated"] <= out["buffers"]["created"], out["buffers"]
    assert out["drawn"][-2] == [20_000, 20_000] and out["drawn"][-1] == [3_000, 3_000]
    assert out["lit"] > 200, "the last cloud is not on the canvas"


async def test_a_cloud_over_the_panel_bound_is_decimated_into_the_buffer(page: Any) -> None:
    out = await page.evaluate(DRAW_CLOUDS_JS, [150_000, 0, 10])
    assert out["mode"] == "webgl", out
    # 150,000 points, every 3rd: 50,000, within the 60,000 the buffers hold; then an
    # empty cloud (a reset draws one) and a tiny one.
    assert out["drawn"] == [[50_000, 50_000], [0, 0], [10, 10]]
    assert out["live"] == out["afterFirst"], out["buffers"]
