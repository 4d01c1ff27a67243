"""The page's ViewerCloud decoder (``static/js/viewercloud.js``) in a real headless Chromium,
fed frames the robot side made: fleetctl.client.viewercloud encodes a cloud, the codec
frames it, fleetctl.wire.compression deflates it; the page's own modules (fb/reader.js,
compression.js with the browser's DecompressionStream) read it back and viewercloud.js
must give the points the Python reference decoder gives."""

from __future__ import annotations

import base64
from typing import Any

import numpy as np
import pytest

from fleetctl.client.viewercloud import VIEWER_CLOUD_TYPE, decode, encode
from fleetctl.wire.codec import Codec
from fleetctl.wire.compression import COMPRESSED_TYPE, CompressionCodec, compress
from fleetctl.wire.registry import TypeRegistry

pytestmark = pytest.mark.browser
TOPIC = "/r1/camera/points/viewer"

# Imports the page's modules from the webviz server, decodes one (maybe compressed) frame
# and returns what viewerCloudXYZ gives, as plain arrays (or the error it raised).
DECODE_JS = """
async ([b64, maxPoints, mutate]) => {
  const { Reader, readMetadata } = await import("/js/fb/reader.js");
  const { Layouts } = await import("/js/fb/layout.js");
  const { COMPRESSED_TYPE, decompress } = await import("/js/compression.js");
  const { VIEWER_CLOUD_TYPE, ViewerCloudError, viewerCloudXYZ } =
    await import("/js/viewercloud.js");
  const layouts = new Layouts();
  for (const t of [COMPRESSED_TYPE, VIEWER_CLOUD_TYPE]) {
    layouts.add(await (await fetch(`/types/${t}.json`)).json());
  }
  const reader = new Reader(layouts);
  let bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const meta = readMetadata(bytes);
  if (meta.type === COMPRESSED_TYPE) {
    bytes = await decompress(meta.topic, reader.decode(bytes, COMPRESSED_TYPE), 1 << 26);
  }
  const msg = reader.decode(bytes, VIEWER_CLOUD_TYPE);
  if (mutate === "short-rgb") msg.rgb = msg.rgb.subarray(1);
  if (mutate === "bad-resolution") msg.resolution_m = 0;
  try {
    const out = viewerCloudXYZ(msg, maxPoints ?? undefined);
    return { type: meta.type, n: out.n, total: out.total, resolution: out.resolution,
             xyz: Array.from(out.xyz), colors: out.colors && Array.from(out.colors) };
  } catch (err) {
    return { error: err instanceof ViewerCloudError ? err.message : `unexpected: ${err}` };
  }
}
"""


def _cloud(registry: TypeRegistry, n: int, colour: bool, seed: int) -> Any:
    """A PointCloud2 of *n* x/y/z(/rgb) float32 points on a noisy sphere of 2 m."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    xyz = (d / np.linalg.norm(d, axis=1, keepdims=True) * 2.0 + rng.normal(0, 0.003, (n, 3))
           + np.array([3.0, -1.0, 0.5])).astype(np.float32)
    xyz[::50] = np.nan  # invalid points, as a depth camera has
    cols = np.zeros((n, 4), np.float32)
    cols[:, :3] = xyz
    cols[:, 3] = rng.integers(0, 1 << 24, n, dtype=np.uint32).view(np.float32)
    field_cls = registry.get("sensor_msgs/msg/PointField").cls
    names = ("x", "y", "z", "rgb") if colour else ("x", "y", "z")
    fields = [field_cls(name, 4 * i, 7, 1) for i, name in enumerate(names)]
    header = registry.get("std_msgs/msg/Header").cls(
        registry.get("builtin_interfaces/msg/Time").cls(5, 0), "camera")
    return registry.get("sensor_msgs/msg/PointCloud2").cls(
        header, 1, n, fields, False, 16, 16 * n, cols.view(np.uint8).reshape(-1), False)


def _frame(codec: Codec, viewer: Any, deflate: bool) -> str:
    frame = codec.encode(viewer, VIEWER_CLOUD_TYPE, TOPIC, seq=1)
    if deflate:
        frame = compress(frame, codec=CompressionCodec.DEFLATE, topic=TOPIC, no_drop=False,
                         frame_codec=codec)
    return base64.b64encode(frame).decode()


async def test_the_page_decodes_a_deflated_viewer_cloud_like_the_python_reference(
    page: Any,
) -> None:
    codec = Codec(TypeRegistry.default())
    viewer = encode(_cloud(codec.registry, 20_000, True, seed=1), 0.01)
    out = await page.evaluate(DECODE_JS, [_frame(codec, viewer, True), None, None])
    assert out.get("error") is None, out
    assert out["type"] == COMPRESSED_TYPE  # it did travel deflated
    xyz, rgb = decode(viewer)
    assert out["n"] == out["total"] == len(xyz) > 5000
    assert out["resolution"] == pytest.approx(0.01, rel=1e-6)
    np.testing.assert_allclose(np.array(out["xyz"]).reshape(-1, 3), xyz, rtol=0, atol=2e-6)
    assert rgb is not None
    np.testing.assert_allclose(np.array(out["colors"]).reshape(-1, 3), rgb / 255.0,
                               rtol=0, atol=1e-6)


async def test_decimation_missing_colours_and_bad_messages(page: Any) -> None:
    codec = Codec(TypeRegistry.default())
    viewer = encode(_cloud(codec.registry, 3000, False, seed=2), 0.05)
    xyz, _ = decode(viewer)
    b64 = _frame(codec, viewer, False)
    out = await page.evaluate(DECODE_JS, [b64, 100, None])
    k = -(-len(xyz) // 100)  # every k-th voxel, as views/cloudpoints.js decimates
    assert out["colors"] is None and out["total"] == len(xyz) and out["n"] <= 100
    np.testing.assert_allclose(np.array(out["xyz"]).reshape(-1, 3), xyz[::k], atol=2e-6)
    coloured = _frame(codec, encode(_cloud(codec.registry, 500, True, seed=3), 0.05), False)
    out = await page.evaluate(DECODE_JS, [coloured, None, "short-rgb"])
    assert "rgb has" in out["error"] and "3 per point or none" in out["error"]
    out = await page.evaluate(DECODE_JS, [b64, None, "bad-resolution"])
    assert out["error"] == "resolution_m is 0"
    empty = encode(_cloud(codec.registry, 0, True, seed=4), 0.01)
    out = await page.evaluate(DECODE_JS, [_frame(codec, empty, False), None, None])
    assert out["n"] == 0 and out["xyz"] == [] and out["colors"] is None
