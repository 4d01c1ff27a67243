"""Runs the JS unit tests (``tests/webviz/js/*.test.mjs``, Node's built-in runner) against
frames the Python codec encoded, then checks with the Python codec the frames the JS
builder encoded: the page and the codec must agree byte for byte on meaning."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from fleetctl.wire.codec import Codec
from fleetctl.wire.compression import COMPRESSED_TYPE, CompressionCodec, compress
from fleetctl.wire.fragments import split
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.samples import occupancy_grid
from fleetctl.wire.schema import describe
from tests.webviz.msgs import to_json, to_plain
from tests.webviz.samples import samples
from tests.webviz.video import encode, h264_codec_string

HERE = Path(__file__).resolve().parent
GOLDEN = HERE.parent / "wire" / "fixtures"
NODE_TIMEOUT_S = 60


def _write_cases(out: Path, registry: TypeRegistry, codec: Codec) -> list[dict[str, object]]:
    (out / "frames").mkdir()
    (out / "types").mkdir()
    cases: list[dict[str, object]] = []
    builds: list[dict[str, object]] = []
    types: set[str] = {"fleetctl_msgs/msg/Fragment"}
    for i, (type_name, topic, msg) in enumerate(samples(registry)):
        frame = codec.encode(
            msg, type_name, topic, seq=i + 1, publish_time_ns=1_700_000_000_123_456_789 + i
        )
        name = f"sample{i}.bin"
        (out / "frames" / name).write_bytes(frame)
        cases.append({"name": name, "type": type_name, "expected": to_json(codec.decode(frame)[1])})
        builds.append(
            {"name": f"built{i}.bin", "type": type_name, "topic": topic, "value": to_plain(msg)}
        )
        types.add(type_name)
    for golden in sorted(GOLDEN.glob("**/*.bin")) if GOLDEN.is_dir() else []:
        meta, msg = codec.decode(golden.read_bytes())
        name = f"golden_{golden.stem}.bin"
        shutil.copy(golden, out / "frames" / name)
        cases.append({"name": name, "type": meta.type, "expected": to_json(msg), "golden": True})
        types.add(meta.type)
    for t in types:
        path = out / "types" / f"{t}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(describe(registry, t)))
    # A point cloud split into fragments, to be reassembled in JS.
    cloud = (out / "frames" / "sample1.bin").read_bytes()
    frags = split(
        cloud, topic="/r1/points", message_id=7, max_fragment_bytes=4096, no_drop=False, codec=codec
    )
    assert len(frags) > 2
    for j, frag in enumerate(frags):
        (out / "frames" / f"frag{j}.bin").write_bytes(frag)
    # The same cloud in fragments of another topic: the page must refuse it (the server
    # checked permissions on the fragments' topic only).
    smuggled = split(
        cloud, topic="/r9/allowed", message_id=8, max_fragment_bytes=4096, no_drop=False,
        codec=codec,
    )
    for j, frag in enumerate(smuggled):
        (out / "frames" / f"smuggled{j}.bin").write_bytes(frag)
    (out / "cases.json").write_text(
        json.dumps(
            {
                "decode": cases,
                "build": builds,
                "fragments": {"count": len(frags), "original": "sample1.bin",
                              "smuggled": len(smuggled)},
                "compressed": _write_compressed(out, codec),
                "video": _write_video(out),
            }
        )
    )
    return builds


def _write_compressed(out: Path, codec: Codec) -> dict[str, object]:
    """A 384 x 384 map compressed as a robot sends it: deflate (fragmented too) and zstd."""
    grid_type = "nav_msgs/msg/OccupancyGrid"
    grid = occupancy_grid(codec.registry)
    original = codec.encode(grid, grid_type, "/r1/map", seq=9, publish_time_ns=1_700_000_000)
    deflated = compress(original, codec=CompressionCodec.DEFLATE, topic="/r1/map", no_drop=False)
    zstd = compress(codec.encode(grid, grid_type, "/r2/map"), codec=CompressionCodec.ZSTD,
                    topic="/r2/map", no_drop=False)
    assert len(deflated) < len(original) / 10 and len(zstd) < len(original) / 10
    frags = split(deflated, topic="/r1/map", message_id=5, max_fragment_bytes=1024,
                  no_drop=False, codec=codec)
    assert len(frags) > 2
    files = {"map_original.bin": original, "map_deflate.bin": deflated, "map_zstd.bin": zstd,
             # A plain frame right behind the compressed one: it must not overtake it.
             "map_plain_after.bin": codec.encode(grid, grid_type, "/r1/map", seq=10)}
    files.update({f"map_frag{j}.bin": f for j, f in enumerate(frags)})
    for name, data in files.items():
        (out / "frames" / name).write_bytes(data)
    values, counts = np.unique(grid.data, return_counts=True)
    for t in (COMPRESSED_TYPE, grid_type):
        path = out / "types" / f"{t}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(describe(codec.registry, t)))
    return {"fragments": len(frags), "width": int(grid.info.width),
            "cells": {str(int(v)): int(c) for v, c in zip(values, counts, strict=True)}}


def _write_video(out: Path) -> list[dict[str, object]]:
    """A few units of each codec a robot may send, with the encoder's keyframe flags."""
    (out / "video").mkdir()
    units: list[dict[str, object]] = []
    for fmt in ("h264", "h265", "vp8", "vp9", "av1"):
        for i, unit in enumerate(encode(fmt, 12, width=160, height=120, keyframe_every=6)):
            name = f"{fmt}_{i}.bin"
            (out / "video" / name).write_bytes(unit.data)
            codec = h264_codec_string(unit.data) if fmt == "h264" and unit.key else None
            units.append({"format": fmt, "name": name, "key": unit.key, "codec": codec})
    assert sum(1 for u in units if u["key"]) >= 10  # each codec: a keyframe at 0 and 6
    return units


@pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed")
def test_js_unit_tests_pass_against_the_python_codec(tmp_path: Path) -> None:
    registry = TypeRegistry.default()
    codec = Codec(registry)
    builds = _write_cases(tmp_path, registry, codec)
    (tmp_path / "built").mkdir()
    env = {**os.environ, "FLEETCTL_WEBVIZ_CASES": str(tmp_path)}
    files = sorted(str(p) for p in (HERE / "js").glob("*.test.mjs"))
    proc = subprocess.run(
        ["node", "--test", *files], env=env, capture_output=True, text=True, timeout=NODE_TIMEOUT_S
    )
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-3000:]
    assert "# fail 0" in proc.stdout
    # The JS builder's frames, decoded by the Python codec, must equal the originals.
    for b in builds:
        frame = (tmp_path / "built" / str(b["name"])).read_bytes()
        meta, msg = codec.decode(frame)
        assert meta.type == b["type"] and meta.topic == b["topic"]
        original = codec.decode(
            (tmp_path / "frames" / str(b["name"]).replace("built", "sample")).read_bytes()
        )[1]
        assert to_json(msg) == to_json(original), b["type"]
