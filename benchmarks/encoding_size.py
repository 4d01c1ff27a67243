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
"""

from __future__ import annotations

import argparse
import base64
import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.layout import FieldKind
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.samples import compressed_image, laser_scan, point_cloud

CASES: list[tuple[str, str, str, Callable[[TypeRegistry], Any]]] = [
    ("LaserScan (720)", "sensor_msgs/msg/LaserScan", "/husky1/scan", laser_scan),
    ("LaserScan (1081, Hokuyo UTM-30LX)", "sensor_msgs/msg/LaserScan", "/husky1/scan",
     lambda registry: laser_scan(registry, 1081)),
    ("PointCloud2 (1 MiB)", "sensor_msgs/msg/PointCloud2", "/husky1/points", point_cloud),
    ("CompressedImage (75 KB)", "sensor_msgs/msg/CompressedImage",
     "/husky1/camera/image/compressed", compressed_image),
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


def render(rows: list[dict[str, Any]]) -> str:
    """A Markdown table of the rows."""
    lines = [
        "| Message | CDR (B) | fleetctl frame (B) | frame - CDR (B) | frame / CDR "
        "| rosbridge JSON (B) | encode (ms) | decode (ms) | CDR ser. (ms) | CDR deser. (ms) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['cdr']:,} | {r['ours']:,} | {r['ours'] - r['cdr']:+,} "
            f"| {r['ours'] / r['cdr']:.4f} | {r['json']:,} "
            f"| {r['encode_s'] * 1e3:.3f} | {r['decode_s'] * 1e3:.3f} "
            f"| {r['cdr_encode_s'] * 1e3:.3f} | {r['cdr_decode_s'] * 1e3:.3f} |"
        )
    return "\n".join(lines)


def main() -> None:
    """Measure and print."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=50, help="iterations per timing")
    args = parser.parse_args()
    print(render(measure(default_codec(), args.repeat)))


if __name__ == "__main__":
    main()
