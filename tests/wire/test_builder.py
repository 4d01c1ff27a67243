"""LeanBuilder writes exactly the bytes of the flatbuffers library's own Builder."""

from __future__ import annotations

import random

import flatbuffers
import pytest

import fleetctl.wire.codec as codec_module
from fleetctl.wire.builder import LeanBuilder
from fleetctl.wire.codec import Codec
from fleetctl.wire.metadata import METADATA_TYPE
from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.samples import point_cloud

from .synth import message

REGISTRY = TypeRegistry.default()
ALL_TYPES = [n for n in REGISTRY.names() if n != METADATA_TYPE]


def encode_all(monkeypatch: pytest.MonkeyPatch, builder_cls: type, start_bytes: int | None,
               seed: int) -> list[bytes]:
    """Every type, random contents, on builders of *builder_cls* (starting at
    *start_bytes* when given, so that every growth path runs)."""
    if start_bytes is not None:
        monkeypatch.setattr(codec_module, "new_builder", lambda _size: builder_cls(start_bytes))
    else:
        monkeypatch.setattr(codec_module, "LeanBuilder", builder_cls)
    codec = Codec(REGISTRY)
    rng = random.Random(seed)
    frames = [codec.encode(message(REGISTRY, name, rng, max_len=seed), name, "/r/t",
                           no_drop=bool(seed % 2), publish_time_ns=seed, seq=seed)
              for name in ALL_TYPES]
    frames.append(codec.encode(point_cloud(REGISTRY), "sensor_msgs/msg/PointCloud2", "/p"))
    monkeypatch.undo()
    return frames


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("start_bytes", [None, 1, 37])
def test_same_bytes_as_the_library_builder(monkeypatch: pytest.MonkeyPatch, seed: int,
                                           start_bytes: int | None) -> None:
    lean = encode_all(monkeypatch, LeanBuilder, start_bytes, seed)
    library = encode_all(monkeypatch, flatbuffers.Builder, start_bytes, seed)
    assert len(lean) == len(ALL_TYPES) + 1
    assert lean == library


def test_the_codec_builds_with_lean_builders() -> None:
    assert isinstance(codec_module.new_builder(64), LeanBuilder)
    assert isinstance(codec_module.new_builder(1 << 20), LeanBuilder)


def test_shared_vtables_and_defaults_match() -> None:
    # Four identical tables share one vtable; zero scalars are left out of the table; a
    # forced default is written. Each step against the library's builder.
    def build(cls: type) -> bytes:
        b = cls(0)
        offsets = []
        for value in (0, 7, 7, 0):
            name = b.CreateString("field")
            b.StartObject(3)
            b.PrependUOffsetTRelativeSlot(0, name, 0)
            b.PrependSlot(flatbuffers.number_types.Int32Flags, 1, value, 0)
            b.PrependSlot(flatbuffers.number_types.Float64Flags, 2, 0.5, 0.0)
            offsets.append(b.EndObject())
        b.StartVector(4, len(offsets), 4)
        for off in reversed(offsets):
            b.PrependUOffsetTRelative(off)
        vector = b.EndVector()
        b.ForceDefaults(True)
        b.StartObject(2)
        b.PrependSlot(flatbuffers.number_types.Uint8Flags, 1, 0, 0)
        b.PrependUOffsetTRelativeSlot(0, vector, 0)
        root = b.EndObject()
        b.Finish(root)
        return bytes(b.Output())

    assert build(LeanBuilder) == build(flatbuffers.Builder)


def test_a_value_that_does_not_fit_still_fails() -> None:
    b = LeanBuilder(16)
    b.StartObject(1)
    with pytest.raises(TypeError):
        b.PrependSlot(flatbuffers.number_types.Uint8Flags, 0, 300, 0)
