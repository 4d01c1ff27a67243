"""Tests of the viewer encoding of point clouds, cross-checked against a plain-Python
reference (one dict entry per voxel, first colour wins) on clouds of every layout."""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
import pytest

from fleetctl.client.config import PublishSpec, ViewerCloudSpec
from fleetctl.client.viewercloud import (
    MAX_INDEX,
    VIEWER_CLOUD_TYPE,
    ViewerCloudError,
    ViewerClouds,
    ViewerCloudStats,
    decode,
    encode,
)
from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.compression import CompressionCodec, compress, decompress

FLOAT32, FLOAT64, UINT32, INT16 = 7, 8, 6, 3


def make_cloud(
    xyz: np.ndarray,
    rgb: np.ndarray | None = None,
    *,
    width: int | None = None,
    float_type: int = FLOAT32,
    bigendian: bool = False,
    point_step: int | None = None,
    row_pad: int = 0,
    colour_field: str = "rgb",
    colour_type: int = FLOAT32,
    order: str = "xyz",
) -> Any:
    """A PointCloud2 of points *xyz* (n, 3) with colours *rgb* (n, 3) uint8, laid out as
    asked: fields in *order* (then the colour), padded points and rows."""
    reg = default_codec().registry
    n = xyz.shape[0]
    width = width or n
    height = n // width if width else 1
    size = 8 if float_type == FLOAT64 else 4
    end = ">" if bigendian else "<"
    names, formats, offsets = [], [], []
    for i, axis in enumerate(order):
        names.append(axis)
        formats.append(f"{end}f{size}")
        offsets.append(i * size + 4)  # 4 leading bytes of padding: offsets are not 0
    if rgb is not None:
        names.append(colour_field)
        formats.append(f"{end}u4")
        offsets.append(3 * size + 8)
    step = point_step or (offsets[-1] + 4 + (size if rgb is None else 0) + 4)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    points = np.zeros(n, dtype)
    for i, axis in enumerate("xyz"):
        points[axis] = xyz[:, i]
    if rgb is not None:
        r, g, b = (rgb[:, i].astype(np.uint32) for i in range(3))
        points[colour_field] = (0xFF << 24) | (r << 16) | (g << 8) | b
    rows = points.view(np.uint8).reshape(height, width * step)
    data = np.concatenate([rows, np.full((height, row_pad), 0xAB, np.uint8)], axis=1)
    field_cls = reg.get("sensor_msgs/msg/PointField").cls
    fields = [field_cls(name, off, float_type, 1) for name, off in zip(names, offsets,
                                                                       strict=False)]
    if rgb is not None:
        fields[-1] = field_cls(colour_field, offsets[-1], colour_type, 1)
    header = reg.get("std_msgs/msg/Header").cls(
        reg.get("builtin_interfaces/msg/Time").cls(12, 34), "camera")
    return reg.get("sensor_msgs/msg/PointCloud2").cls(
        header, height, width, fields, bigendian, step, width * step + row_pad,
        data.reshape(-1), False)


def reference(xyz: np.ndarray, rgb: np.ndarray | None, msg: Any) -> list[tuple[Any, ...]]:
    """Voxels of the finite points with the first colour of each, sorted, in plain Python,
    using the message's own origin and resolution."""
    res = float(np.float32(msg.resolution_m))
    origin = (float(msg.origin_x), float(msg.origin_y), float(msg.origin_z))
    voxels: dict[tuple[int, ...], tuple[int, ...]] = {}
    for i, p in enumerate(xyz.tolist()):
        if not all(math.isfinite(v) for v in p):
            continue
        key = tuple(min(MAX_INDEX, math.floor((v - o) / res)) for v, o in zip(p, origin,
                                                                            strict=True))
        if key not in voxels:
            voxels[key] = tuple(int(c) for c in rgb[i]) if rgb is not None else ()
    return sorted((*k, *c) for k, c in voxels.items())


def encoded(msg: Any) -> list[tuple[Any, ...]]:
    n = len(msg.xyz) // 3
    idx = np.asarray(msg.xyz).reshape(3, n).T.tolist()
    cols = np.asarray(msg.rgb).reshape(3, n).T.tolist() if len(msg.rgb) else [[]] * n
    return [(*i, *c) for i, c in zip(idx, cols, strict=True)]


def random_cloud(n: int = 3000, seed: int = 1, scale: float = 0.3) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    # Clustered around a few surfaces so many points share voxels, as a camera's do.
    xyz = np.round(rng.normal(0.0, scale, (n, 3)) * 200) / 200 + np.array([1.0, -2.0, 0.5])
    rgb = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    return xyz, rgb


def check_error_bound(xyz: np.ndarray, msg: Any) -> None:
    """Every finite point lies within res * sqrt(3) / 2 of the decoded centre of its voxel."""
    centres, _ = decode(msg)
    lookup = {tuple(k): i for i, k in enumerate(np.asarray(msg.xyz).reshape(3, -1).T.tolist())}
    res = float(np.float32(msg.resolution_m))
    origin = np.array([msg.origin_x, msg.origin_y, msg.origin_z])
    finite = xyz[np.isfinite(xyz).all(axis=1)]
    for p in finite:
        key = tuple(int(v) for v in np.floor((p - origin) / res))
        assert np.linalg.norm(p - centres[lookup[key]]) <= res * math.sqrt(3) / 2 + 1e-9


def test_matches_the_reference_and_is_sorted_unique_and_within_the_bound() -> None:
    xyz, rgb = random_cloud()
    stats = ViewerCloudStats()
    msg = encode(make_cloud(xyz, rgb), 0.01, stats=stats)
    assert encoded(msg) == reference(xyz.astype(np.float32).astype(np.float64), rgb, msg)
    idx = [tuple(v[:3]) for v in encoded(msg)]
    assert idx == sorted(set(idx))
    assert np.asarray(msg.xyz).dtype == np.int16 and np.asarray(msg.rgb).dtype == np.uint8
    assert msg.header.frame_id == "camera" and msg.header.stamp.sec == 12
    assert np.float32(msg.resolution_m) == np.float32(0.01)
    low = xyz.astype(np.float32).min(axis=0)
    assert np.all(np.array([msg.origin_x, msg.origin_y, msg.origin_z], np.float32) <= low)
    assert stats.clouds == 1 and stats.points_in == 3000 and stats.points_nonfinite == 0
    assert stats.points_out == len(idx) < 3000  # duplicates were merged
    check_error_bound(xyz.astype(np.float32).astype(np.float64), msg)


@pytest.mark.parametrize("layout", [
    {"float_type": FLOAT64},
    {"bigendian": True},
    {"bigendian": True, "float_type": FLOAT64},
    {"point_step": 48},
    {"width": 60, "row_pad": 12},  # organized 60 x 50 with padded rows
    {"order": "zyx"},  # fields in another order
    {"colour_field": "rgba", "colour_type": UINT32},
])
def test_every_layout_reads_the_same_points(layout: dict[str, Any]) -> None:
    xyz, rgb = random_cloud(seed=2)
    if layout.get("float_type") != FLOAT64:
        xyz = xyz.astype(np.float32).astype(np.float64)
    msg = encode(make_cloud(xyz, rgb, **layout), 0.02)
    assert encoded(msg) == reference(xyz, rgb, msg)


def test_non_finite_points_are_dropped_and_counted() -> None:
    xyz, rgb = random_cloud(n=1000, seed=3)
    xyz[::7, 0] = np.nan
    xyz[1::11, 2] = np.inf
    xyz[2::13, 1] = -np.inf
    bad = int((~np.isfinite(xyz).all(axis=1)).sum())
    stats = ViewerCloudStats()
    msg = encode(make_cloud(xyz, rgb, width=100), 0.01, stats=stats)
    assert stats.points_nonfinite == bad > 0
    assert encoded(msg) == reference(xyz.astype(np.float32).astype(np.float64), rgb, msg)


def test_without_colour_the_rgb_plane_is_empty() -> None:
    xyz, _ = random_cloud(n=500, seed=4)
    msg = encode(make_cloud(xyz), 0.05)
    assert len(msg.rgb) == 0 and len(msg.xyz) > 0
    assert decode(msg)[1] is None
    assert encoded(msg) == reference(xyz.astype(np.float32).astype(np.float64), None, msg)


def test_a_cloud_too_wide_for_int16_is_coarsened_not_cut() -> None:
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-250.0, 250.0, (2000, 3))  # 500 m: 50,000 voxels of 1 cm
    xyz[0] = (-250.0, -250.0, -250.0)
    xyz[1] = (250.0, 250.0, 250.0)
    xyz = xyz.astype(np.float32).astype(np.float64)
    stats = ViewerCloudStats()
    msg = encode(make_cloud(xyz), 0.01, stats=stats)
    assert stats.coarsened == 1
    assert 500.0 / MAX_INDEX < msg.resolution_m < 1.01 * 500.0 / MAX_INDEX
    idx = np.asarray(msg.xyz).reshape(3, -1)
    assert idx.min() >= 0 and idx.max() <= MAX_INDEX
    assert len(msg.xyz) // 3 == 2000  # every point kept (they are far apart)
    check_error_bound(xyz, msg)


def test_empty_and_all_invalid_clouds_give_empty_messages() -> None:
    xyz = np.full((10, 3), np.nan)
    for cloud in (make_cloud(xyz, np.zeros((10, 3), np.uint8)), make_cloud(np.empty((0, 3)))):
        msg = encode(cloud, 0.01)
        assert len(msg.xyz) == 0 and len(msg.rgb) == 0
        assert decode(msg)[0].shape == (0, 3)


def test_clouds_that_cannot_be_read_raise_errors_naming_the_field() -> None:
    xyz, _ = random_cloud(n=10)
    cloud = make_cloud(xyz)
    no_z = make_cloud(xyz)
    no_z.fields = [f for f in no_z.fields if f.name != "z"]
    with pytest.raises(ViewerCloudError, match=r"no z field \(fields: x, y\)"):
        encode(no_z, 0.01)
    int_x = make_cloud(xyz)
    int_x.fields[0].datatype = INT16
    with pytest.raises(ViewerCloudError, match="field x has datatype 3"):
        encode(int_x, 0.01)
    short = make_cloud(xyz)
    short.data = short.data[:-short.point_step]  # the last point is cut
    with pytest.raises(ViewerCloudError, match="data is"):
        encode(short, 0.01)
    outside = make_cloud(xyz)
    outside.fields[2].offset = cloud.point_step - 2
    with pytest.raises(ViewerCloudError, match="field z at offset"):
        encode(outside, 0.01)
    zero_step = make_cloud(xyz)
    zero_step.point_step = 0
    with pytest.raises(ViewerCloudError, match="point_step is 0"):
        encode(zero_step, 0.01)
    with pytest.raises(ViewerCloudError, match="resolution_m"):
        encode(cloud, 0.0)


def test_survives_the_wire_with_deflate() -> None:
    codec = Codec(default_codec().registry)
    xyz, rgb = random_cloud(n=20_000, seed=6, scale=1.0)
    msg = encode(make_cloud(xyz, rgb, width=200), 0.01)
    frame = codec.encode(msg, VIEWER_CLOUD_TYPE, "/r1/points/viewer", seq=3)
    packed = compress(frame, codec=CompressionCodec.DEFLATE, topic="/r1/points/viewer",
                      no_drop=False, frame_codec=codec)
    assert len(packed) < len(frame)
    meta, back = codec.decode(decompress(packed, 1 << 24, frame_codec=codec))
    assert meta.type == VIEWER_CLOUD_TYPE
    assert encoded(back) == encoded(msg)
    assert np.float32(back.origin_x) == np.float32(msg.origin_x)


# --- the client's hook -----------------------------------------------------------------------


def spec(**kw: Any) -> PublishSpec:
    base: dict[str, Any] = {
        "topic": "/camera/points", "type": "sensor_msgs/msg/PointCloud2", "priority": 2.5,
        "rate_limit_hz": 5.0, "no_drop": True, "remote_topic": "/r1/camera/points",
        "compression": "none", "viewer_cloud": ViewerCloudSpec(resolution_m=0.05)}
    return PublishSpec(**{**base, **kw})


def test_the_hook_sends_a_droppable_deflated_viewer_topic_at_the_clouds_priority() -> None:
    sent: list[tuple[PublishSpec, Any, bool]] = []

    def send(s: PublishSpec, msg: Any, *, latched: bool = False) -> bool:
        sent.append((s, msg, latched))
        return True

    hook = ViewerClouds(send)
    xyz, rgb = random_cloud(n=400)
    assert hook.on_cloud(spec(), make_cloud(xyz, rgb), latched=True)
    (out_spec, msg, latched), = sent
    assert out_spec.remote_topic == "/r1/camera/points/viewer"
    assert out_spec.type == VIEWER_CLOUD_TYPE and out_spec.compression == "deflate"
    assert out_spec.priority == 2.5 and out_spec.rate_limit_hz == 5.0
    assert not out_spec.no_drop and out_spec.viewer_cloud is None and latched
    assert np.float32(msg.resolution_m) == np.float32(0.05)
    assert hook.viewer_spec(spec()) is out_spec  # cached
    assert not hook.on_cloud(spec(viewer_cloud=None), make_cloud(xyz, rgb))


def test_the_hook_logs_a_bad_cloud_once_per_topic_and_counts_every_one(
    caplog: pytest.LogCaptureFixture,
) -> None:
    hook = ViewerClouds(lambda *a, **k: pytest.fail("nothing must be sent"))
    bad = make_cloud(random_cloud(n=10)[0])
    bad.fields = bad.fields[:1]
    with caplog.at_level(logging.DEBUG, logger="fleetctl.client.viewercloud"):
        for _ in range(3):
            assert not hook.on_cloud(spec(), bad)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert "/camera/points" in warnings[0].getMessage()
    assert "no y/z field" in warnings[0].getMessage()
    assert hook.stats.errors == 3
