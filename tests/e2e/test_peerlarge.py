"""The peer-large scenario's analysis on hand-made samples."""

from __future__ import annotations

import pytest

from fleetctl.e2e import peerlarge
from fleetctl.e2e.samples import Sample

S = 1_000_000_000
MS = 1_000_000
POSE, IMAGE = peerlarge.POSE, "/robot1/camera/image/compressed"
HZ = {POSE: 20.0, IMAGE: 3.0}


def _samples(pose_ms: float, image_ms: float, sizes: tuple[int, int], *,
             images_every: int = 1, seconds: int = 10) -> list[Sample]:
    out = []
    for i in range(20 * seconds):
        pub = i * S // 20
        out.append(Sample(POSE, i, pub, pub + int(pose_ms * MS), sizes[0]))
    for i in range(3 * seconds):
        if i % images_every == 0:
            pub = i * S // 3
            out.append(Sample(IMAGE, i, pub, pub + int(image_ms * MS), sizes[1]))
    return out


def _run(samples: list[Sample], uplink_bit_s: float) -> peerlarge.LargeRun:
    return peerlarge.LargeRun(samples, 10.0, uplink_bit_s, HZ)


def test_bytes_per_cdr_byte_and_the_pose_are_compared_with_the_better_zenoh() -> None:
    # CDR: the pose 80 B, the image 100,000 B: 301,600 B/s delivered.
    cdr_Bps = 20 * 80 + 3 * 100_000
    runs = {
        "fleetctl": _run(_samples(3.0, 300.0, (260, 100_180)), 8 * cdr_Bps * 1.10),
        "zenoh-default": _run(_samples(90.0, 400.0, (80, 100_000)), 8 * cdr_Bps * 1.04),
        "zenoh-best": _run(_samples(40.0, 350.0, (80, 100_000)), 8 * cdr_Bps * 1.05),
    }
    result = peerlarge.peer_large(runs)
    crits = {c["name"]: c for c in result["criteria"]}
    ratio = crits["fleetctl / zenoh's fewest uplink bytes per CDR byte delivered"]
    assert ratio["value"] == pytest.approx(1.10 / 1.04)
    assert not ratio["ok"] and result["status"] == "fail"
    pose = crits["fleetctl pose p99 while the images flow / zenoh's lowest"]
    assert pose["value"] == pytest.approx(3.0 / 40.0) and pose["ok"]
    fleet = result["variants"]["fleetctl"]
    assert fleet["wire_per_cdr_byte"] == pytest.approx(1.10)
    assert fleet["topics"][IMAGE]["delivered"] == pytest.approx(1.0)
    assert any("bytes on the uplink per CDR byte" in n for n in result["notes"])


def test_images_lost_count_against_the_bytes_and_the_delivery() -> None:
    # Half the images delivered for the same uplink: twice the bytes per CDR byte.
    runs = {"fleetctl": _run(_samples(3.0, 300.0, (260, 100_180), images_every=2), 2.4e6),
            "zenoh-best": _run(_samples(40.0, 350.0, (80, 100_000)), 2.4e6)}
    figs = peerlarge.peer_large(runs)["variants"]
    assert figs["fleetctl"]["topics"][IMAGE]["delivered"] == pytest.approx(0.5)
    assert figs["fleetctl"]["wire_per_cdr_byte"] == pytest.approx(
        figs["zenoh-best"]["wire_per_cdr_byte"] * (20 * 80 + 3 * 100_000)
        / (20 * 80 + 1.5 * 100_000), rel=1e-3)


def test_without_a_zenoh_variant_the_frames_stand_for_the_cdr() -> None:
    runs = {"fleetctl": _run(_samples(3.0, 300.0, (260, 100_180)), 2.5e6)}
    assert peerlarge.cdr_bytes(runs) == {POSE: 260, IMAGE: 100_180}
