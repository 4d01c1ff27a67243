"""Runs the JS unit tests (``tests/webviz/js/*.test.mjs``, Node's built-in runner) against
frames the Python codec encoded, then checks with the Python codec the frames the JS
builder encoded: the page and the codec must agree byte for byte on meaning."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from fleetctl.wire.codec import Codec
from fleetctl.wire.fragments import split
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.schema import describe
from tests.webviz.msgs import to_json, to_plain
from tests.webviz.samples import samples

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
    (out / "cases.json").write_text(
        json.dumps(
            {
                "decode": cases,
                "build": builds,
                "fragments": {"count": len(frags), "original": "sample1.bin"},
            }
        )
    )
    return builds


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
