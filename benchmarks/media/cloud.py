"""Point cloud bandwidth: the full PointCloud2 against its viewer encoding (ViewerCloud).

Usage::

    .venv/bin/python benchmarks/media/cloud.py [--frames 5] [--resolution 0.01] [--json]

The case of the Robot Web Tools paper (section IV-C, Table II): an ASUS Xtion Pro RGB-D
camera streamed for 2 minutes, 5,591.6 KB/s as ROS point clouds against 568.4 KB/s as
its depth-in-video web encoding (9.8x). The paper gives neither the cloud's size nor its
rate, so the rate here is the one at which our full cloud costs RWT's 5,591.6 KB/s as a
plain frame (about 0.57 Hz for 9.8 MB clouds): both rows then have the same input, and the
ratio is what carries over.

The cloud (the same every run, seeded): what ``depth_image_proc/point_cloud_xyzrgb`` makes
of a Kinect-class camera, organized 640 x 480, fields x y z rgb float32 at offsets 0 4 8
16 and 32-byte points (PCL's PointXYZRGB layout: the 4th float is 1.0, 12 bytes of zero
padding after rgb), NaN x/y/z where the depth is invalid. The scene, ray-cast per pixel
(fx = fy = 525, the ROS default Kinect intrinsics) from 1 m above the floor, tilted 12
degrees down: a room corner (floor, three walls), a table with a box and a ball on it, a
cabinet. Surfaces carry real photographs from scikit-image's bundled data (astronaut,
coffee, chelsea, rocket, brick and grass textures) at 250 px/m, shaded, plus 2 levels of
colour noise. Depth as a structured-light sensor measures it: disparity (baseline 7.5 cm)
with 0.056 px of noise (Khoshelham's 1.425e-3 z^2 m) quantized to 1/8 px, no depth under
0.5 m or over 4.0 m, shadows left of near edges as wide as the disparity step (the
projector's offset), 0.5 % random dropouts (3.3 % of the pixels invalid in all). Each
frame pans the camera by a few degrees and draws new noise.

Measured per frame, as the wire carries it (``fleetctl.wire.codec.Codec`` frames, metadata
included; deflate is ``fleetctl.wire.compression`` at its shipped level): the full cloud
plain and deflated, the viewer cloud plain and deflated (what the client sends), points
kept, CPU time per cloud (one thread: encode, and encode + frame + deflate), and the
largest distance from any valid input point to the decoded centre of its voxel (bound:
resolution * sqrt(3) / 2). Every valid point's voxel is checked to be present. KB = 1000
bytes.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from fleetctl.client import viewercloud
from fleetctl.client.viewercloud import VIEWER_CLOUD_TYPE
from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.compression import CompressionCodec, compress

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
TOPIC = "/robot/camera/depth_registered/points"
RWT_FULL_KBPS = 5591.6  # RWT Table II, "ROS Internal"
RWT_WEB_KBPS = 568.4  # RWT Table II, "Web Streaming"
WIDTH, HEIGHT = 640, 480
FX = FY = 525.0
CX, CY = 319.5, 239.5
BASELINE_M = 0.075
DISPARITY_NOISE_PX = 1.425e-3 * FX * BASELINE_M  # Khoshelham: sigma_z = 1.425e-3 z^2
MIN_DEPTH_M, MAX_DEPTH_M = 0.5, 4.0
POINT_STEP = 32
TEXTURE_PX_PER_M = 250.0
Array = npt.NDArray[Any]


@dataclass(frozen=True)
class Box:
    """An axis-aligned box in the world frame (x right, y down, z forward), metres."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    texture: str


# World frame: camera at the origin, 1 m above the floor (y down, so the floor is y = 1).
WALLS = [  # (axis, position, texture): infinite planes, the room's surfaces
    (1, 1.0, "brick"), (2, 3.6, "astronaut"), (0, -1.8, "rocket"), (0, 2.2, "chelsea"),
]
BOXES = [
    Box((-0.7, 0.22, 1.3), (0.5, 0.27, 2.1), "coffee"),  # table top
    *(Box((x, 0.27, z), (x + 0.05, 1.0, z + 0.05), "grass")
      for x in (-0.68, 0.43) for z in (1.32, 2.03)),  # table legs
    Box((-0.4, -0.05, 1.5), (-0.1, 0.22, 1.8), "astronaut"),  # a box on the table
    Box((1.0, 0.2, 2.4), (1.8, 1.0, 3.2), "coffee"),  # a cabinet
]
BALL = ((0.25, 0.1, 1.7), 0.12, "chelsea")


def _textures() -> dict[str, Array]:
    from skimage import data

    def rgb(name: str, tint: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> Array:
        img: Array = np.asarray(getattr(data, name)())  # bundled with scikit-image
        if img.ndim == 2:
            img = np.repeat(img[:, :, None], 3, axis=2)
        out: Array = np.clip(img[:, :, :3].astype(np.float64) * np.array(tint), 0, 255)
        return out

    return {
        "astronaut": rgb("astronaut"), "coffee": rgb("coffee"), "chelsea": rgb("chelsea"),
        "rocket": rgb("rocket"), "brick": rgb("brick", (1.0, 0.75, 0.6)),
        "grass": rgb("grass", (0.6, 1.0, 0.5)),
    }


def _rays(pan_rad: float, tilt_rad: float) -> tuple[Array, Array]:
    """Per-pixel ray directions: camera frame (z = 1) and world frame, shape (3, H*W)."""
    u, v = np.meshgrid(np.arange(WIDTH, dtype=np.float64), np.arange(HEIGHT, dtype=np.float64))
    cam = np.stack([(u.ravel() - CX) / FX, (v.ravel() - CY) / FY, np.ones(u.size)])
    ct, st, cp, sp = math.cos(tilt_rad), math.sin(tilt_rad), math.cos(pan_rad), math.sin(pan_rad)
    tilt = np.array([[1, 0, 0], [0, ct, st], [0, -st, ct]])  # positive: looks down
    pan = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    return cam, pan @ tilt @ cam


def _trace(world: Array, textures: dict[str, Array]) -> tuple[Array, Array]:
    """Ray-cast the scene: ``(t, rgb)``, t the camera-frame depth (inf: no hit)."""
    n = world.shape[1]
    best = np.full(n, np.inf)
    uv = np.zeros((2, n))
    tex = np.full(n, -1)
    shade = np.ones(n)
    names = list(textures)

    def hit(t: Array, a: Array, b: Array, name: str, light: float | Array) -> None:
        closer = (t > 1e-6) & (t < best)
        best[closer] = t[closer]
        uv[0, closer], uv[1, closer] = a[closer], b[closer]
        tex[closer] = names.index(name)
        shade[closer] = np.broadcast_to(light, t.shape)[closer]

    with np.errstate(divide="ignore", invalid="ignore"):
        for axis, pos, name in WALLS:
            t = pos / world[axis]
            p = world * t
            a, b = [p[i] for i in range(3) if i != axis]
            hit(t, a, b, name, 0.8 + 0.1 * axis)
        for box in BOXES:
            _hit_box(world, box, hit)
        (c, r, name) = BALL
        oc = -np.array(c)[:, None]
        bq = (world * oc).sum(0)
        cq = (oc * oc).sum() - r * r
        aq = (world * world).sum(0)
        disc = bq * bq - aq * cq
        t = np.where(disc >= 0, (-bq - np.sqrt(np.maximum(disc, 0))) / aq, np.inf)
        p = world * t
        normal = (p - np.array(c)[:, None]) / r
        hit(t, np.arctan2(normal[0], normal[2]) * r, p[1], name,
            0.5 + 0.5 * np.clip(-normal[1] * 0.6 - normal[2] * 0.8, 0, 1))
    return best, _colour(uv, tex, shade, textures)


def _hit_box(world: Array, box: Box, hit: Any) -> None:
    lo, hi = np.array(box.lo)[:, None], np.array(box.hi)[:, None]
    t1, t2 = lo / world, hi / world
    near = np.minimum(t1, t2)
    far = np.maximum(t1, t2)
    t_in = near.max(0)
    face = near.argmax(0)
    t = np.where((t_in <= far.min(0)) & (t_in > 0), t_in, np.inf)
    p = world * t
    for axis in range(3):
        on = face == axis
        a, b = [p[i] for i in range(3) if i != axis]
        hit(np.where(on, t, np.inf), a, b, box.texture, 0.7 + 0.1 * axis)


def _colour(uv: Array, tex: Array, shade: Array, textures: dict[str, Array]) -> Array:
    out = np.zeros((uv.shape[1], 3))
    for i, img in enumerate(textures.values()):
        sel = tex == i
        h, w = img.shape[:2]
        col = (uv[0, sel] * TEXTURE_PX_PER_M).astype(np.int64) % w
        row = (uv[1, sel] * TEXTURE_PX_PER_M).astype(np.int64) % h
        out[sel] = img[row, col] * shade[sel, None]
    return out


def _measure_depth(t: Array, rng: np.random.Generator) -> Array:
    """Structured-light depth from true depth *t* (inf: no return): NaN where invalid."""
    fb = FX * BASELINE_M
    with np.errstate(divide="ignore"):
        disparity = fb / t + rng.normal(0.0, DISPARITY_NOISE_PX, t.size)
        z = fb / (np.round(disparity * 8.0) / 8.0)
    z[~np.isfinite(t) | (z < MIN_DEPTH_M) | (z > MAX_DEPTH_M) | (disparity <= 0)] = np.nan
    depth = z.reshape(HEIGHT, WIDTH)
    # The projector sits 7.5 cm beside the IR camera: a background pixel whose pattern a
    # nearer surface k pixels to its right blocks gets none (the shadow is as wide as the
    # disparity step).
    with np.errstate(divide="ignore"):
        true_disparity = (fb / t).reshape(HEIGHT, WIDTH)
    shadow = np.zeros_like(depth, dtype=bool)
    for k in range(1, 41):
        shadow[:, :-k] |= true_disparity[:, k:] - true_disparity[:, :-k] > k
    depth[shadow] = np.nan
    depth.reshape(-1)[rng.random(depth.size) < 0.005] = np.nan
    return depth.reshape(-1)


def camera_cloud(codec: Codec, frame: int = 0, seed: int = 7) -> Any:
    """One 640 x 480 x/y/z/rgb PointCloud2 of the scene (see the module docstring).

    Args:
        codec: Its registry gives the message classes.
        frame: Frame number: the camera pans by ``3 * sin(frame)`` degrees.
        seed: Noise seed (combined with *frame*).
    """
    rng = np.random.default_rng([seed, frame])
    cam, world = _rays(math.radians(3.0 * math.sin(frame)), math.radians(12.0))
    t, rgb = _trace(world, _textures())
    z = _measure_depth(t, rng)
    xyz = (cam * z).T  # NaN rows stay NaN
    rgb = np.clip(rgb + rng.normal(0.0, 2.0, rgb.shape), 0, 255).astype(np.uint32)
    points = np.zeros((WIDTH * HEIGHT, POINT_STEP // 4), np.float32)
    points[:, :3] = xyz
    points[:, 3] = 1.0  # PCL's PointXYZRGB: the 4th float of the position is 1
    points[:, 4] = ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).view(np.float32)
    reg = codec.registry
    field_cls = reg.get("sensor_msgs/msg/PointField").cls
    fields = [field_cls(name, off, 7, 1) for name, off in (("x", 0), ("y", 4), ("z", 8),
                                                           ("rgb", 16))]
    header = reg.get("std_msgs/msg/Header").cls(
        reg.get("builtin_interfaces/msg/Time").cls(1_700_000_000 + frame, 0),
        "camera_rgb_optical_frame")
    return reg.get(CLOUD_TYPE).cls(header, HEIGHT, WIDTH, fields, False, POINT_STEP,
                                   POINT_STEP * WIDTH, points.view(np.uint8).reshape(-1), False)


def check_error(cloud: Any, viewer: Any) -> tuple[float, int]:
    """``(max_error_m, missing)``: the largest distance from a valid input point to its
    voxel's decoded centre, and how many valid points have no voxel in *viewer*."""
    pts = cloud.data.view(np.float32).reshape(-1, POINT_STEP // 4)[:, :3].astype(np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    centres, _ = viewercloud.decode(viewer)
    res = float(np.float32(viewer.resolution_m))
    origin = np.array([viewer.origin_x, viewer.origin_y, viewer.origin_z], np.float64)
    index = np.floor((pts - origin) / res).astype(np.int64)
    sent = np.asarray(viewer.xyz, np.int64).reshape(3, -1)
    shape = (1 << 16, 1 << 16)  # indices are 0..32767: a flat key per voxel
    keys_sent = np.ravel_multi_index((sent[0], np.ravel_multi_index(sent[1:], shape)),
                                     (1 << 16, 1 << 32))
    keys = np.ravel_multi_index((index[:, 0], np.ravel_multi_index(index[:, 1:].T, shape)),
                                (1 << 16, 1 << 32))
    pos = np.searchsorted(keys_sent, keys)
    found = (pos < keys_sent.size) & (keys_sent[np.minimum(pos, keys_sent.size - 1)] == keys)
    err = np.linalg.norm(pts[found] - centres[pos[found]], axis=1)
    return float(err.max(initial=0.0)), int(np.count_nonzero(~found))


def measure_cloud(frames: int = 5, resolution_m: float = 0.01, codec: Codec | None = None,
                  rate_hz: float | None = None, repeat: int = 5) -> dict[str, Any]:
    """Encode *frames* camera clouds both ways and measure them.

    Args:
        frames: Clouds to average over.
        resolution_m: Viewer voxel edge, metres.
        codec: The frame codec (default: fleetctl's default registry).
        rate_hz: Cloud rate for the KB/s figures (None: the rate at which the plain full
            frame costs RWT's 5,591.6 KB/s).
        repeat: Timed encodings per cloud.

    Returns:
        A JSON-able dict: per-frame sizes (bytes, means), ``*_kBps`` at ``rate_hz``,
        ``ratio`` (full deflated / viewer deflated) and ``ratio_plain`` (full plain /
        viewer deflated), points, ``encode_ms`` (:func:`viewercloud.encode`) and
        ``send_ms`` (plus framing and deflate; medians of thread CPU time, ms per cloud),
        ``max_error_m`` and its bound,
        ``missing_points`` (valid points without a voxel: 0).
    """
    codec = codec or default_codec()
    viewer_cls = codec.registry.get(VIEWER_CLOUD_TYPE).cls
    sizes: dict[str, list[int]] = {k: [] for k in ("full", "full_deflate", "viewer",
                                                    "viewer_deflate")}
    times: dict[str, list[float]] = {"encode": [], "send": []}
    points, valid, kept, errors, missing = [], [], [], [], 0
    for i in range(frames):
        cloud = camera_cloud(codec, i)
        full = codec.encode(cloud, CLOUD_TYPE, TOPIC, seq=i + 1)
        stats = viewercloud.ViewerCloudStats()
        for _ in range(repeat):  # CPU time of one thread: the robot's cost
            start = time.thread_time()
            viewer = viewercloud.encode(cloud, resolution_m, cls=viewer_cls)
            mid = time.thread_time()
            frame = codec.encode(viewer, VIEWER_CLOUD_TYPE, TOPIC + "/viewer", seq=i + 1)
            packed = _deflate(frame, TOPIC + "/viewer", codec)
            times["encode"].append((mid - start) * 1000)
            times["send"].append((time.thread_time() - start) * 1000)
        viewercloud.encode(cloud, resolution_m, cls=viewer_cls, stats=stats)
        for key, value in (("full", full), ("full_deflate", _deflate(full, TOPIC, codec)),
                           ("viewer", frame), ("viewer_deflate", packed)):
            sizes[key].append(len(value))
        points.append(stats.points_in)
        valid.append(stats.points_in - stats.points_nonfinite)
        kept.append(stats.points_out)
        err, miss = check_error(cloud, viewer)
        errors.append(err)
        missing += miss
    mean = {k: statistics.fmean(v) for k, v in sizes.items()}
    rate = rate_hz if rate_hz is not None else RWT_FULL_KBPS * 1000 / mean["full"]
    return {
        "frames": frames, "resolution_m": resolution_m, "rate_hz": rate,
        "points": statistics.fmean(points), "valid_points": statistics.fmean(valid),
        "kept_points": statistics.fmean(kept),
        **{f"{k}_bytes": v for k, v in mean.items()},
        **{f"{k}_kBps": v * rate / 1000 for k, v in mean.items()},
        "ratio": mean["full_deflate"] / mean["viewer_deflate"],
        "ratio_plain": mean["full"] / mean["viewer_deflate"],
        "encode_ms": statistics.median(times["encode"]),
        "send_ms": statistics.median(times["send"]),
        "max_error_m": max(errors), "error_bound_m": resolution_m * math.sqrt(3) / 2,
        "missing_points": missing,
        "rwt_full_kBps": RWT_FULL_KBPS, "rwt_web_kBps": RWT_WEB_KBPS,
    }


def _deflate(frame: bytes, topic: str, codec: Codec) -> bytes:
    return compress(frame, codec=CompressionCodec.DEFLATE, topic=topic, no_drop=False,
                    frame_codec=codec)


def render(r: dict[str, Any]) -> str:
    """The result as a small text table."""
    rows = [("full cloud, plain", "full"), ("full cloud, deflate", "full_deflate"),
            ("viewer cloud, plain", "viewer"), ("viewer cloud, deflate (sent)", "viewer_deflate")]
    return "\n".join([
        f"Point cloud, 640x480 x/y/z/rgb (32-byte points), {r['frames']} frames, "
        f"viewer at {r['resolution_m'] * 100:g} cm, {r['rate_hz']:.3f} Hz",
        f"{'':30}{'KB/frame':>10}{'KB/s':>10}",
        *(f"{name:30}{r[k + '_bytes'] / 1000:10.1f}{r[k + '_kBps']:10.1f}" for name, k in rows),
        f"reduction {r['ratio']:.1f}x against the deflated full cloud, {r['ratio_plain']:.1f}x "
        f"against the plain one (RWT: {RWT_FULL_KBPS:,} -> {RWT_WEB_KBPS} KB/s, "
        f"{RWT_FULL_KBPS / RWT_WEB_KBPS:.1f}x)",
        f"points: {r['points']:.0f}, valid {r['valid_points']:.0f}, kept {r['kept_points']:.0f}",
        f"CPU per cloud (median): encode {r['encode_ms']:.1f} ms, + frame + deflate "
        f"{r['send_ms']:.1f} ms",
        f"max position error {r['max_error_m'] * 1000:.2f} mm (bound "
        f"{r['error_bound_m'] * 1000:.2f} mm), valid points without a voxel: "
        f"{r['missing_points']}",
    ])


def main() -> None:
    """Measure and print."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=5, help="clouds to average over")
    parser.add_argument("--resolution", type=float, default=0.01, help="voxel edge, metres")
    parser.add_argument("--rate", type=float, default=None,
                        help="cloud rate in Hz (default: RWT's full-cloud bandwidth)")
    parser.add_argument("--json", action="store_true", help="print JSON")
    args = parser.parse_args()
    result = measure_cloud(args.frames, args.resolution, rate_hz=args.rate)
    print(json.dumps(result, indent=2) if args.json else render(result))


if __name__ == "__main__":
    main()
