"""Encoded size and cost of the fleetctl wire format vs ROS 2 CDR and rosbridge JSON.

Usage::

    .venv/bin/python benchmarks/encoding_size.py [--repeat 50]

Prints a table like Table I of the Robofleet paper: for realistic messages (a 720-beam
LaserScan with intensities, a 32 x 2048 PointCloud2 of 1 MiB, a 75 KB JPEG
CompressedImage), the ROS 2 CDR size (``rosbags`` ``serialize_cdr``, including the 4-byte
encapsulation header), our frame size (the whole WebSocket payload: metadata with type,
topic, seq and publish time included), and the size of a rosbridge ``publish`` JSON
message (uint8 arrays as base64, as rosbridge sends them).
Then the mean encode and decode time per message of both codecs.

A second table measures per-topic compression (``fleetctl.wire.compression``, the whole
path: compress + Compressed frame, and decode + decompress + checks) on the messages worth
compressing: a 384 x 384 SLAM-like OccupancyGrid, the 1 MiB PointCloud2, the demo sim's
cloud of 20,000 wall points, and the 720-beam LaserScan. ``--levels`` adds a table of the
raw codecs at the levels considered (zstd 1 and 3, deflate 1 and 6).
"""

from __future__ import annotations

import argparse
import base64
import functools
import json
import time
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np
import zstandard

from fleetctl.client.ros.simworld import MotionConfig as SimMotion
from fleetctl.client.ros.simworld import (
    RoomConfig,
    points_in_robot_frame,
    room_points,
    start_state,
)
from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.compression import CompressionCodec, compress, decompress
from fleetctl.wire.layout import FieldKind
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.samples import compressed_image, laser_scan, occupancy_grid, point_cloud

CASES: list[tuple[str, str, str, Callable[[TypeRegistry], Any]]] = [
    ("LaserScan (720)", "sensor_msgs/msg/LaserScan", "/husky1/scan", laser_scan),
    ("LaserScan (1081, Hokuyo UTM-30LX)", "sensor_msgs/msg/LaserScan", "/husky1/scan",
     lambda registry: laser_scan(registry, 1081)),
    ("PointCloud2 (1 MiB)", "sensor_msgs/msg/PointCloud2", "/husky1/points", point_cloud),
    ("CompressedImage (75 KB)", "sensor_msgs/msg/CompressedImage",
     "/husky1/camera/image/compressed", compressed_image),
]


def sim_cloud(registry: TypeRegistry) -> Any:
    """The demo sim's ``/points``: 20,000 xyz float32 points on the room's walls."""
    room = RoomConfig()
    xyz = points_in_robot_frame(room_points(room, 20_000), start_state(room, SimMotion(), 0.3))
    field_cls = registry.get("sensor_msgs/msg/PointField").cls
    fields = [field_cls(name, 4 * i, 7, 1) for i, name in enumerate("xyz")]
    return registry.get("sensor_msgs/msg/PointCloud2").cls(
        registry.get("std_msgs/msg/Header").cls(
            registry.get("builtin_interfaces/msg/Time").cls(0, 0), "base_link"),
        1, len(xyz), fields, False, 12, 12 * len(xyz), xyz.view(np.uint8).reshape(-1), True)


COMPRESSION_CASES: list[tuple[str, str, str, Callable[[TypeRegistry], Any]]] = [
    ("OccupancyGrid (384 x 384)", "nav_msgs/msg/OccupancyGrid", "/husky1/map", occupancy_grid),
    ("PointCloud2 (1 MiB)", "sensor_msgs/msg/PointCloud2", "/husky1/points", point_cloud),
    ("PointCloud2 (demo sim, 20k wall points)", "sensor_msgs/msg/PointCloud2",
     "/husky1/points", sim_cloud),
    ("LaserScan (720)", "sensor_msgs/msg/LaserScan", "/husky1/scan", laser_scan),
]


def to_rosbridge(registry: TypeRegistry, msg: Any, type_name: str) -> Any:
    """The JSON-able form rosbridge would publish (byte arrays base64, numbers as lists)."""
    out: dict[str, Any] = {}
    for f in registry.get(type_name).fields:
        value = getattr(msg, f.name)
        if f.kind in (FieldKind.TABLE, FieldKind.STRUCT):
            assert f.ref is not None
            out[f.name] = to_rosbridge(registry, value, f.ref)
        elif f.kind in (FieldKind.TABLE_VECTOR, FieldKind.STRUCT_VECTOR):
            assert f.ref is not None
            out[f.name] = [to_rosbridge(registry, v, f.ref) for v in value]
        elif f.kind is FieldKind.SCALAR_VECTOR:
            if value.dtype == np.uint8:
                out[f.name] = base64.b64encode(value.tobytes()).decode()
            else:
                out[f.name] = value.tolist()
        else:
            out[f.name] = value
    return out


def _mean_s(fn: Callable[[], object], repeat: int) -> float:
    fn()  # warm up (first call generates the per-type encoder/decoder)
    start = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - start) / repeat


def measure_case(
    codec: Codec, label: str, type_name: str, topic: str, msg: Any, repeat: int
) -> dict[str, Any]:
    """Sizes in bytes and mean times in seconds per message for one message."""
    registry, store = codec.registry, codec.registry.typestore
    now_ns = time.time_ns()

    def encode() -> bytes:
        return codec.encode(msg, type_name, topic, publish_time_ns=now_ns, seq=123_456)

    frame = encode()
    cdr = bytes(store.serialize_cdr(msg, type_name))
    envelope = {"op": "publish", "topic": topic, "msg": to_rosbridge(registry, msg, type_name)}
    return {
        "label": label, "cdr": len(cdr), "ours": len(frame),
        "json": len(json.dumps(envelope, separators=(",", ":"))),
        "encode_s": _mean_s(encode, repeat),
        "decode_s": _mean_s(lambda: codec.decode(frame), repeat),
        "cdr_encode_s": _mean_s(lambda: store.serialize_cdr(msg, type_name), repeat),
        "cdr_decode_s": _mean_s(lambda: store.deserialize_cdr(cdr, type_name), repeat),
    }


def measure(codec: Codec, repeat: int) -> list[dict[str, Any]]:
    """One row per case of :data:`CASES`."""
    return [
        measure_case(codec, label, type_name, topic, make(codec.registry), repeat)
        for label, type_name, topic, make in CASES
    ]


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table: the first column left-aligned, the others right-aligned."""
    def line(cells: list[str]) -> str:
        return "| " + " | ".join(cells) + " |"

    return "\n".join([line(header), "|---|" + "---:|" * (len(header) - 1),
                      *(line(r) for r in rows)])


def render(rows: list[dict[str, Any]]) -> str:
    """A Markdown table of the rows."""
    header = ["Message", "CDR (B)", "fleetctl frame (B)", "frame - CDR (B)", "frame / CDR",
              "rosbridge JSON (B)", "encode (ms)", "decode (ms)", "CDR ser. (ms)",
              "CDR deser. (ms)"]
    return markdown_table(header, [
        [r["label"], f"{r['cdr']:,}", f"{r['ours']:,}", f"{r['ours'] - r['cdr']:+,}",
         f"{r['ours'] / r['cdr']:.4f}", f"{r['json']:,}", f"{r['encode_s'] * 1e3:.3f}",
         f"{r['decode_s'] * 1e3:.3f}", f"{r['cdr_encode_s'] * 1e3:.3f}",
         f"{r['cdr_decode_s'] * 1e3:.3f}"]
        for r in rows
    ])


def measure_compression(codec: Codec, repeat: int) -> list[dict[str, Any]]:
    """Per case of :data:`COMPRESSION_CASES`: frame sizes (bytes) and mean times (s)."""
    rows = []
    for label, type_name, topic, make in COMPRESSION_CASES:
        frame = codec.encode(make(codec.registry), type_name, topic,
                             publish_time_ns=time.time_ns(), seq=123_456)
        row: dict[str, Any] = {"label": label, "original": len(frame)}
        for method in CompressionCodec:
            row.update(_compression_cells(codec, label, frame, topic, method, repeat))
        rows.append(row)
    return rows


def _compression_cells(codec: Codec, label: str, frame: bytes, topic: str,
                       method: CompressionCodec, repeat: int) -> dict[str, Any]:
    key = method.name.lower()

    def pack() -> bytes:
        return compress(frame, codec=method, topic=topic, no_drop=False, frame_codec=codec)

    packed = pack()
    assert packed is not frame, f"{label}: {key} saved under 5 %"
    assert decompress(packed, len(frame), frame_codec=codec) == frame
    return {
        key: len(packed),
        f"{key}_compress_s": _mean_s(pack, repeat),
        f"{key}_decompress_s": _mean_s(
            lambda: decompress(packed, len(frame), frame_codec=codec), repeat),
    }


def render_compression(rows: list[dict[str, Any]]) -> str:
    """A Markdown table of the compression rows (ratio = original / compressed frame)."""
    header = ["Message", "frame (B)"]
    for name in ("zstd", "deflate"):
        header += [f"{name} (B)", "ratio", "compress (ms)", "decompress (ms)"]
    table = []
    for r in rows:
        cells = [r["label"], f"{r['original']:,}"]
        for key in ("zstd", "deflate"):
            cells += [f"{r[key]:,}", f"{r['original'] / r[key]:.2f}",
                      f"{r[key + '_compress_s'] * 1e3:.3f}",
                      f"{r[key + '_decompress_s'] * 1e3:.3f}"]
        table.append(cells)
    return markdown_table(header, table)


LEVELS: list[tuple[str, Callable[[bytes], bytes]]] = [
    ("zstd 1", zstandard.ZstdCompressor(level=1).compress),
    ("zstd 3", zstandard.ZstdCompressor(level=3).compress),
    ("deflate 1", lambda data: zlib.compress(data, 1, wbits=-15)),
    ("deflate 6", lambda data: zlib.compress(data, 6, wbits=-15)),
]


def render_levels(codec: Codec, repeat: int) -> str:
    """Raw codecs on the encoded frames: compressed size / original, and ms per message."""
    header = ["Message"] + [cell for name, _ in LEVELS for cell in (f"{name} size", f"{name} ms")]
    table = []
    for label, type_name, topic, make in COMPRESSION_CASES:
        frame = codec.encode(make(codec.registry), type_name, topic)
        cells = [label]
        for _name, fn in LEVELS:
            cells += [f"{len(fn(frame)) / len(frame):.3f}",
                      f"{_mean_s(functools.partial(fn, frame), repeat) * 1e3:.3f}"]
        table.append(cells)
    return markdown_table(header, table)


def main() -> None:
    """Measure and print."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=50, help="iterations per timing")
    parser.add_argument("--compression-repeat", type=int, default=20,
                        help="iterations per compression timing")
    parser.add_argument("--levels", action="store_true", help="also compare codec levels")
    args = parser.parse_args()
    codec = default_codec()
    print(render(measure(codec, args.repeat)))
    print()
    print(render_compression(measure_compression(codec, args.compression_repeat)))
    if args.levels:
        print()
        print(render_levels(codec, args.compression_repeat))


if __name__ == "__main__":
    main()
