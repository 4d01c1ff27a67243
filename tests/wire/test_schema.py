"""Schema export checked by the real flatc, and flatc-generated Python reading our bytes.

flatc's Python output is an independent FlatBuffers implementation: if it reads, field by
field, the values our encoder wrote, our layout is the layout the ``.fbs`` files describe.
"""

from __future__ import annotations

import importlib
import json
import random
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.layout import FieldKind, MessageLayout
from fleetctl.wire.metadata import METADATA_TYPE
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.schema import describe, export_fbs, fbs_path, fbs_qualified_name

from .synth import message

FLATC = shutil.which("flatc") or str(Path(sys.executable).with_name("flatc"))
ALL_TYPES = [n for n in default_codec().registry.names() if n != METADATA_TYPE]


@pytest.fixture(scope="module")
def flatc_python(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Every known type exported, compiled by flatc --python, importable as ``fb``."""
    if not Path(FLATC).exists():
        pytest.fail(f"flatc not found at {FLATC} (the dev extra installs it)")
    schema_dir = tmp_path_factory.mktemp("fbs")
    out_dir = tmp_path_factory.mktemp("fbs_py")
    files = export_fbs(default_codec().registry, None, schema_dir)
    result = subprocess.run(
        [FLATC, "--python", "-o", str(out_dir), "-I", str(schema_dir), *map(str, files)],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert result.returncode == 0, result.stderr + result.stdout
    saved = {k: v for k, v in sys.modules.items() if k == "fb" or k.startswith("fb.")}
    sys.path.insert(0, str(out_dir))
    try:
        yield out_dir
    finally:
        sys.path.remove(str(out_dir))
        for key in [k for k in sys.modules if k == "fb" or k.startswith("fb.")]:
            del sys.modules[key]
        sys.modules.update(saved)


def _generated_class(layout: MessageLayout, *, as_table: bool) -> Any:
    qualified = fbs_qualified_name(layout, as_table=as_table)
    module: ModuleType = importlib.import_module(qualified)
    return getattr(module, qualified.rsplit(".", 1)[1])


def _accessor(obj: Any, field_name: str) -> Any:
    """flatc's accessor of a field (it CamelCases names: ``angle_min`` -> ``AngleMin``)."""
    wanted = field_name.replace("_", "").lower()
    for attr in dir(obj):
        if attr.replace("_", "").lower() == wanted and callable(getattr(obj, attr)):
            return getattr(obj, attr)
    raise AssertionError(f"flatc generated no accessor for {field_name} on {type(obj)}")


def _same_scalar(theirs: Any, ours: Any, ros: str) -> None:
    if ros == "float32":
        assert np.float32(theirs) == np.float32(ours)
    elif ros == "bool":
        assert bool(theirs) == bool(ours)
    else:
        assert theirs == ours


def _check_struct(registry: TypeRegistry, theirs: Any, ours: Any, name: str) -> None:
    for f in registry.get(name).fields:
        assert f.scalar is not None
        _same_scalar(_accessor(theirs, f.fbs_name)(), getattr(ours, f.name), f.scalar.ros)


def _check_table(registry: TypeRegistry, theirs: Any, ours: Any, name: str) -> None:
    for f in registry.get(name).fields:
        get = _accessor(theirs, f.fbs_name)
        value = getattr(ours, f.name)
        kind = f.kind
        if kind is FieldKind.SCALAR:
            assert f.scalar is not None
            _same_scalar(get(), value, f.scalar.ros)
        elif kind is FieldKind.STRING:
            assert (get() or b"").decode() == value
        elif kind is FieldKind.STRUCT:
            assert f.ref is not None
            _check_struct(registry, get(), value, f.ref)
        elif kind is FieldKind.TABLE:
            assert f.ref is not None
            _check_table(registry, get(), value, f.ref)
        elif kind is FieldKind.SCALAR_VECTOR:
            assert f.scalar is not None
            theirs_array = _accessor(theirs, f.fbs_name + "AsNumpy")()
            theirs_array = np.zeros(0) if isinstance(theirs_array, int) else theirs_array
            assert np.array_equal(theirs_array.astype(f.scalar.dtype), value)
        else:
            count = _accessor(theirs, f.fbs_name + "Length")()
            assert count == len(value)
            for i, item in enumerate(value):
                if kind is FieldKind.STRING_VECTOR:
                    assert get(i).decode() == item
                elif kind is FieldKind.STRUCT_VECTOR:
                    assert f.ref is not None
                    _check_struct(registry, get(i), item, f.ref)
                else:
                    assert f.ref is not None
                    _check_table(registry, get(i), item, f.ref)


@pytest.mark.parametrize("name", ALL_TYPES)
def test_flatc_generated_python_reads_our_frames(
    flatc_python: Path, codec: Codec, name: str
) -> None:
    registry = codec.registry
    layout = registry.get(name)
    cls = _generated_class(layout, as_table=True)
    msg = message(registry, name, random.Random(len(name)), max_len=3)
    frame = codec.encode(msg, name, "/husky1/x", no_drop=True, publish_time_ns=17, seq=4)
    root = cls.GetRootAs(frame, 0)
    meta = _accessor(root, "__metadata")()
    assert (meta.Type().decode(), meta.Topic().decode(), meta.NoDrop(), meta.PublishTimeNs(),
            meta.Seq()) == (name, "/husky1/x", True, 17, 4)
    _check_table(registry, root, msg, name)


def test_export_of_chosen_types_includes_dependencies(tmp_path: Path, codec: Codec) -> None:
    files = export_fbs(codec.registry, ["sensor_msgs/PointCloud2"], tmp_path)
    rel = {str(p.relative_to(tmp_path)) for p in files}
    assert rel == {fbs_path(n) for n in (
        "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/PointField", "std_msgs/msg/Header",
        "builtin_interfaces/msg/Time", METADATA_TYPE)}
    result = subprocess.run(
        [FLATC, "--python", "-o", str(tmp_path / "py"), "-I", str(tmp_path),
         str(tmp_path / "sensor_msgs/msg/PointCloud2.fbs")],
        capture_output=True, text=True, timeout=60, check=False,
    )
    assert result.returncode == 0, result.stderr


def test_describe_is_json_and_matches_the_layout(codec: Codec) -> None:
    layout = describe(codec.registry, "nav_msgs/Odometry")
    assert json.loads(json.dumps(layout)) == layout
    assert layout["root"] == "nav_msgs/msg/Odometry"
    odom = layout["tables"]["nav_msgs/msg/Odometry"]
    assert odom["first_slot"] == 1
    assert odom["fields"][0] == {"name": "header", "slot": 1, "kind": "table",
                                 "type": "std_msgs/msg/Header"}
    cov = layout["tables"]["geometry_msgs/msg/PoseWithCovariance"]["fields"][1]
    assert cov == {"name": "covariance", "slot": 2, "kind": "scalar_vector",
                   "element": "float64", "element_bytes": 8, "fixed_len": 36}
    assert layout["structs"]["builtin_interfaces/msg/Time"] == {
        "size_bytes": 8, "align_bytes": 4,
        "fields": [{"name": "sec", "offset": 0, "element": "int32"},
                   {"name": "nanosec", "offset": 4, "element": "uint32"}]}
    assert layout["tables"][METADATA_TYPE]["first_slot"] == 0


def test_the_cross_check_notices_a_wrong_value(flatc_python: Path, codec: Codec) -> None:
    registry = codec.registry
    msg = message(registry, "sensor_msgs/msg/LaserScan", random.Random(1), max_len=3)
    frame = codec.encode(msg, "sensor_msgs/msg/LaserScan", "/t")
    root = _generated_class(registry.get("sensor_msgs/msg/LaserScan"), as_table=True).GetRootAs(
        frame, 0)
    msg.header.frame_id += "x"
    with pytest.raises(AssertionError):
        _check_table(registry, root, msg, "sensor_msgs/msg/LaserScan")
