"""Map size on the wire: a 2,725 KB-class occupancy grid, plain, deflated and zstd'd.

Usage::

    .venv/bin/python benchmarks/media/map.py [--json]

The case of the Robot Web Tools paper (section IV-D, Table III): a 732 x 413 map of 2,725
KB as rosbridge JSON, 39 KB with rosbridge's PNG compression. Our frame of the same grid is
a tenth of that already (one byte per cell, no JSON), so the "2,725 KB class" here is a
grid whose frame is that large: 1650 x 1650 cells (2,723 KB), a 82.5 m square at 5 cm.
The RWT-sized grid (732 x 413) is measured too.

The map (the same every run, seeded; numpy only): what a 2D SLAM (slam_toolbox, gmapping)
saves after a tour, not a drawing. A floor plan (an office building: outer walls, two
corridors, rooms of random widths on both sides with doors, a quarter of them closed,
furniture as solid blocks and table legs, pillars) is scanned from a robot path (corridor
centrelines every metre, into each open room and around it) with a 720-beam lidar (12 m
range, 1.5 cm range noise, 1 % of beams lost); cells accumulate log-odds along each beam
(free) and at its end (occupied), and are thresholded as map_saver does (occupied >= 0.65,
free <= 0.196, else unknown -1). So: unknown outside and in closed rooms, ragged frontiers,
wall thickness from noise, shadows behind furniture.

Measured: the ``nav_msgs/msg/OccupancyGrid`` frame (``fleetctl.wire.codec.Codec``, metadata
included) and the Compressed frames of ``fleetctl.wire.compression`` with deflate (what a
latched map gets, and what the page inflates) and zstd at the shipped levels, with the
compression time. KB = 1000 bytes.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import time
from typing import Any

import numpy as np
import numpy.typing as npt
import zstandard

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.compression import LATCHED_DEFLATE_LEVEL, CompressionCodec, compress

GRID_TYPE = "nav_msgs/msg/OccupancyGrid"
TOPIC = "/robot/map"
RWT_ORIGINAL_KB = 2725.0  # RWT Table III, map 732 x 413, rosbridge JSON
RWT_COMPRESSED_KB = 39.0  # ... PNG-compressed
RESOLUTION_M = 0.05
BEAMS = 720
RANGE_M = 12.0
RANGE_NOISE_M = 0.015
LOST_BEAMS = 0.01
L_FREE, L_OCC = -0.4, 0.85  # log-odds per observation (gmapping-like)
P_OCC, P_FREE = 0.65, 0.196  # map_saver's thresholds
Cells = npt.NDArray[np.bool_]


def floor_plan(width: int, height: int, rng: np.random.Generator) -> tuple[Cells, list[Any]]:
    """``(walls, path)``: the true occupied cells (rows = y) and the robot's path (cells)."""
    walls = np.zeros((height, width), bool)
    m = max(8, min(width, height) // 16)  # outside margin
    x0, x1, y0, y1 = m, width - m, m, height - m
    t = 3  # 15 cm walls

    def block(xa: int, ya: int, xb: int, yb: int) -> None:
        walls[max(ya, 0):max(yb, 0), max(xa, 0):max(xb, 0)] = True

    for xa, ya, xb, yb in ((x0, y0, x1, y0 + t), (x0, y1 - t, x1, y1), (x0, y0, x0 + t, y1),
                           (x1 - t, y0, x1, y1)):
        block(xa, ya, xb, yb)
    half = 30  # 3 m corridors
    strips = max(1, (y1 - y0) // 480)  # each: rooms, a corridor, rooms (~10 m deep)
    bounds = np.linspace(y0, y1, strips + 1).astype(int)
    path: list[Any] = []
    for sa, sb in itertools.pairwise(bounds):
        block(x0, sb - t // 2, x1, sb - t // 2 + t)  # the wall between strips
        cy = (sa + sb) // 2
        for side in (-1, 1):
            wall_y = cy + side * half
            block(x0, wall_y, x1, wall_y + t)
            path += _rooms(walls, (x0, x1), wall_y, sa if side < 0 else sb, rng)
        for px in range(x0 + 100, x1 - 50, 200):  # pillars along the corridor
            yy, xx = np.ogrid[-6:7, -6:7]
            walls[cy - 6:cy + 7, px - 6:px + 7] |= yy * yy + xx * xx <= 30
        path += [(float(x), float(cy - 15)) for x in range(x0 + 20, x1 - 20, 20)]
        path += [(float(x), float(cy + 15)) for x in range(x1 - 30, x0 + 20, -20)]
    return walls, path


def _rooms(walls: Cells, span: tuple[int, int], wall_y: int, outer: int,
           rng: np.random.Generator) -> list[Any]:
    """Rooms between a corridor wall and *outer*, doors in the corridor wall (a quarter
    closed); returns the robot's path through the open ones."""
    x0, x1 = span
    t, path, x = 3, [], x0
    lo, hi = min(wall_y, outer), max(wall_y, outer)
    while x < x1 - 60:
        xb = min(x + int(rng.integers(120, 200)), x1)
        if x1 - xb < 60:
            xb = x1
        walls[lo:hi, xb - t:xb] = True
        door = int(rng.integers(x + 20, xb - 40))
        if rng.random() >= 0.25:
            walls[wall_y:wall_y + t, door:door + 18] = False
            room = (x + t, lo + t, xb - t, hi - t)
            _furnish(walls, room, rng)
            path += _room_path((door + 9, wall_y + t // 2), room)
        x = xb
    return path


def _furnish(walls: Cells, room: tuple[int, int, int, int], rng: np.random.Generator) -> None:
    xa, ya, xb, yb = room
    for _ in range(int(rng.integers(2, 6))):
        w, h = (int(v) for v in rng.integers(8, 30, 2))
        if xb - xa <= w + 12 or yb - ya <= h + 12:
            continue
        x = int(rng.integers(xa + 4, xb - w - 4))
        y = int(rng.integers(ya + 4, yb - h - 4))
        if rng.random() < 0.5:  # a cabinet: solid
            walls[y:y + h, x:x + w] = True
        else:  # a table: four legs
            for lx, ly in ((x, y), (x + w - 2, y), (x, y + h - 2), (x + w - 2, y + h - 2)):
                walls[ly:ly + 2, lx:lx + 2] = True


def _room_path(door: tuple[int, int], room: tuple[int, int, int, int]) -> list[Any]:
    """From the corridor through the door to the room's centre (a pose every 0.5 m) and
    around it (8 poses)."""
    xa, ya, xb, yb = room
    cx, cy = (xa + xb) / 2, (ya + yb) / 2
    steps = max(2, int(math.hypot(cx - door[0], cy - door[1]) / 10))
    path = [(door[0] + (cx - door[0]) * i / steps, door[1] + (cy - door[1]) * i / steps)
            for i in range(steps + 1)]
    rx, ry = max(10.0, (xb - xa) / 4), max(10.0, (yb - ya) / 4)
    path += [(cx + rx * math.cos(a), cy + ry * math.sin(a))
             for a in np.linspace(0, 2 * math.pi, 8, endpoint=False)]
    return path


def scan_map(walls: Cells, path: list[Any], rng: np.random.Generator) -> npt.NDArray[np.int8]:
    """Occupancy values (-1, 0, 100) after scanning *walls* from every pose of *path*."""
    height, width = walls.shape
    logodds = np.zeros(walls.size)
    angles = np.linspace(0.0, 2 * math.pi, BEAMS, endpoint=False)
    steps = np.arange(0.0, RANGE_M / RESOLUTION_M, 0.7)  # samples along a beam, cells
    dx, dy = np.cos(angles)[:, None] * steps, np.sin(angles)[:, None] * steps
    for px, py in path:
        if walls[int(py), int(px)]:
            continue
        xs, ys = (px + dx).astype(np.int64), (py + dy).astype(np.int64)
        inside = (xs >= 0) & (xs < width) & (ys >= 0) & (ys < height)
        hit = np.zeros(xs.shape, bool)
        hit[inside] = walls[ys[inside], xs[inside]]
        first = np.where(hit.any(axis=1), hit.argmax(axis=1), -1)
        noisy = first + np.round(rng.normal(0.0, RANGE_NOISE_M / RESOLUTION_M / 0.7,
                                            BEAMS)).astype(np.int64)
        ok = (first >= 0) & (rng.random(BEAMS) >= LOST_BEAMS)
        end = np.clip(np.where(ok, noisy, 0), 0, steps.size - 1)
        free = (np.arange(steps.size)[None, :] < end[:, None]) & inside & ok[:, None]
        cells_free = np.unique(ys[free] * width + xs[free])
        beams = np.flatnonzero(ok & inside[np.arange(BEAMS), end])
        cells_hit = np.unique(ys[beams, end[beams]] * width + xs[beams, end[beams]])
        logodds[cells_free] += L_FREE
        logodds[cells_hit] += L_OCC - L_FREE  # the end cell was also passed as free
    p = 1.0 - 1.0 / (1.0 + np.exp(logodds))
    out = np.full(walls.size, -1, np.int8)
    seen = logodds != 0
    out[seen & (p >= P_OCC)] = 100
    out[seen & (p <= P_FREE)] = 0
    return out


def occupancy_grid(codec: Codec, width: int, height: int, seed: int = 3) -> Any:
    """The ``nav_msgs/msg/OccupancyGrid`` of the module docstring, *width* x *height*."""
    rng = np.random.default_rng(seed)
    walls, path = floor_plan(width, height, rng)
    cells = scan_map(walls, path, rng)
    reg = codec.registry
    stamp = reg.get("builtin_interfaces/msg/Time").cls(1_700_000_000, 0)
    origin = reg.get("geometry_msgs/msg/Pose").cls(
        reg.get("geometry_msgs/msg/Point").cls(-width * RESOLUTION_M / 2,
                                               -height * RESOLUTION_M / 2, 0.0),
        reg.get("geometry_msgs/msg/Quaternion").cls(0.0, 0.0, 0.0, 1.0))
    info = reg.get("nav_msgs/msg/MapMetaData").cls(stamp, RESOLUTION_M, width, height, origin)
    header = reg.get("std_msgs/msg/Header").cls(stamp, "map")
    return reg.get(GRID_TYPE).cls(header, info, cells)


def measure_one(codec: Codec, width: int, height: int) -> dict[str, Any]:
    """Sizes (bytes) and compression times (ms) of one grid's frames."""
    grid = occupancy_grid(codec, width, height)
    frame = codec.encode(grid, GRID_TYPE, TOPIC, seq=1)
    out: dict[str, Any] = {"width": width, "height": height, "frame_bytes": len(frame)}
    values, counts = np.unique(grid.data, return_counts=True)
    out["cells"] = {str(int(v)): int(c) for v, c in zip(values, counts, strict=True)}
    for name, kind in (("deflate", CompressionCodec.DEFLATE), ("zstd", CompressionCodec.ZSTD)):
        start = time.perf_counter()
        packed = compress(frame, codec=kind, topic=TOPIC, no_drop=False, frame_codec=codec)
        out[f"{name}_ms"] = (time.perf_counter() - start) * 1000
        out[f"{name}_bytes"] = len(packed)
    # What the robot client sends for a latched map (the bridge's latched path: deflate at
    # LATCHED_DEFLATE_LEVEL, a whole Compressed frame) and zstd-9's payload for comparison.
    latched = codec.encode(grid, GRID_TYPE, TOPIC, seq=1, latched=True)
    start = time.perf_counter()
    packed = compress(latched, codec=CompressionCodec.DEFLATE, topic=TOPIC, no_drop=False,
                      frame_codec=codec, level=LATCHED_DEFLATE_LEVEL)
    out["latched_deflate_ms"] = (time.perf_counter() - start) * 1000
    out["latched_deflate_bytes"] = len(packed)
    out["zstd9_payload_bytes"] = len(zstandard.ZstdCompressor(level=9).compress(frame))
    return out


def measure_map(codec: Codec | None = None) -> dict[str, Any]:
    """Both grids (1650 x 1650 and RWT's 732 x 413).

    Returns:
        A JSON-able dict: ``large`` and ``rwt_size`` (each: width, height, cell counts,
        ``frame_bytes``, ``deflate_bytes``/``_ms``, ``zstd_bytes``/``_ms``) and RWT's figures.
    """
    codec = codec or default_codec()
    return {"large": measure_one(codec, 1650, 1650), "rwt_size": measure_one(codec, 732, 413),
            "rwt_original_kB": RWT_ORIGINAL_KB, "rwt_compressed_kB": RWT_COMPRESSED_KB}


def render(r: dict[str, Any]) -> str:
    """The result as a small text table."""
    lines = [f"Occupancy grid at {RESOLUTION_M * 100:g} cm (RWT: {RWT_ORIGINAL_KB:,} KB JSON -> "
             f"{RWT_COMPRESSED_KB:g} KB PNG, 732 x 413)",
             f"{'':14}{'frame KB':>10}{'deflate KB':>12}{'ms':>7}{'zstd KB':>10}{'ms':>7}"
             f"{'latched':>9}{'ms':>7}{'zstd-9':>9}"]
    for m in (r["large"], r["rwt_size"]):
        lines.append(f"{m['width']} x {m['height']:<7}{m['frame_bytes'] / 1000:10.1f}"
                     f"{m['deflate_bytes'] / 1000:12.1f}{m['deflate_ms']:7.1f}"
                     f"{m['zstd_bytes'] / 1000:10.1f}{m['zstd_ms']:7.1f}"
                     f"{m['latched_deflate_bytes'] / 1000:9.1f}{m['latched_deflate_ms']:7.1f}"
                     f"{m['zstd9_payload_bytes'] / 1000:9.1f}")
    cells = r["large"]["cells"]
    total = sum(cells.values())
    lines.append("1650 x 1650 cells: " + ", ".join(
        f"{name} {100 * cells.get(v, 0) / total:.1f} %"
        for v, name in (("-1", "unknown"), ("0", "free"), ("100", "occupied"))))
    lines.append("deflate/zstd: Compressed frames at the streams' level 1; latched: the "
                 f"client's latched path (deflate level {LATCHED_DEFLATE_LEVEL}, Compressed "
                 "frame); zstd-9: payload only")
    return "\n".join(lines)


def main() -> None:
    """Measure and print."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", action="store_true", help="print JSON")
    args = parser.parse_args()
    result = measure_map()
    print(json.dumps(result, indent=2) if args.json else render(result))


if __name__ == "__main__":
    main()
