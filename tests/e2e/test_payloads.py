"""Test messages carry their stamp through the real codec and CDR (no ROS needed)."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from fleetctl.e2e import payloads, profiles
from fleetctl.e2e.consumer import Recorder
from fleetctl.e2e.samples import load
from fleetctl.errors import FleetError
from fleetctl.wire.codec import default_codec
from fleetctl.wire.fragments import split

T_NS = 1_700_000_000_123_456_789


@pytest.mark.parametrize("type_name", sorted(payloads.BUILDERS))
def test_stamp_survives_cdr_and_the_wire(type_name: str) -> None:
    codec = default_codec()
    ts = codec.registry.typestore
    msg = payloads.build(ts, type_name, 5000, 42, T_NS)
    back = ts.deserialize_cdr(ts.serialize_cdr(msg, type_name), type_name)
    _, decoded = codec.decode(codec.encode(back, type_name, "/robot1/x"))
    assert payloads.read_stamp(decoded) == payloads.Stamp(42, T_NS)


def test_size_is_close_to_requested() -> None:
    ts = default_codec().registry.typestore
    for type_name in ("sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/PointCloud2",
                      "std_msgs/msg/String", "sensor_msgs/msg/LaserScan"):
        cdr = ts.serialize_cdr(payloads.build(ts, type_name, 65_536, 1, T_NS), type_name)
        assert 65_536 <= len(cdr) <= 65_536 + 200, type_name


def test_scans_look_like_a_lidar_and_differ_from_scan_to_scan() -> None:
    """Byte counts and compression measured with these scans must mean something: whole
    millimetres and counts, noise, a few beams without a return, and no two alike."""
    import zlib

    import numpy as np

    ranges, counts = payloads.scan_readings(720, 7)
    again, _ = payloads.scan_readings(720, 7)
    other, _ = payloads.scan_readings(720, 8)
    assert ranges.dtype == counts.dtype == np.float32 and len(ranges) == len(counts) == 720
    assert np.array_equal(ranges, again, equal_nan=True)  # deterministic in seq
    finite = np.isfinite(ranges)
    assert 0.95 < finite.mean() < 1.0  # about 1 % without a return (+inf)
    assert np.allclose(ranges[finite] * 1000, np.round(ranges[finite] * 1000), atol=1e-2)
    assert np.array_equal(counts, np.round(counts)) and counts.min() >= 0
    assert (ranges != other).mean() > 0.9  # noise: a new scan, not the same bytes
    assert ranges[finite].min() > 0.1 and ranges[finite].max() < 30.0
    raw = ranges.tobytes() + counts.tobytes()
    ratio = len(zlib.compress(raw, 9)) / len(raw)
    assert 0.45 < ratio < 0.8  # compressible as real scans are, not to nothing


def test_camera_frames_are_4_3_rgb8_and_move() -> None:
    ts = default_codec().registry.typestore
    assert payloads.camera_size(640 * 480 * 3) == (640, 480)
    assert payloads.camera_size(5000) == (48, 36)
    a, b = (payloads.build(ts, "sensor_msgs/msg/Image", 640 * 480 * 3, i, T_NS)
            for i in (1, 2))
    assert (a.width, a.height, a.encoding, a.step) == (640, 480, "rgb8", 1920)
    assert len(a.data) == 640 * 480 * 3
    assert (a.data != b.data).mean() > 0.5  # motion and noise: most pixels change


def test_video_frames_carry_the_source_stamp() -> None:
    codec = default_codec()
    video = codec.registry.typestore.types["foxglove_msgs/msg/CompressedVideo"]
    image = payloads.build(codec.registry.typestore, "sensor_msgs/msg/Image", 5000, 9, T_NS)
    msg = video(timestamp=image.header.stamp, frame_id=image.header.frame_id,
                data=np.zeros(4, np.uint8), format="h264")
    assert payloads.read_stamp(msg) == payloads.Stamp(9, T_NS)


def test_unknown_type_and_unstamped_message_are_clear_errors() -> None:
    ts = default_codec().registry.typestore
    with pytest.raises(FleetError, match="no test message builder"):
        payloads.build(ts, "nav_msgs/msg/Odometry", 10, 1, 0)
    with pytest.raises(FleetError, match="not an e2e test message"):
        payloads.read_stamp(ts.types["std_msgs/msg/String"](data="hello"))


def test_recorder_reassembles_fragments_and_drops_resent_no_drop() -> None:
    codec = default_codec()
    ts = codec.registry.typestore
    out = io.StringIO()
    rec = Recorder("c0", out)
    image = payloads.build(ts, "sensor_msgs/msg/CompressedImage", 50_000, 7, T_NS)
    frame = codec.encode(image, "sensor_msgs/msg/CompressedImage", "/robot1/img")
    parts = split(frame, topic="/robot1/img", message_id=1, max_fragment_bytes=4096,
                  no_drop=False)
    assert len(parts) > 1
    results = [rec.feed(p, T_NS + 5_000_000) for p in parts]
    assert results[:-1] == [None] * (len(parts) - 1)
    assert results[-1] is not None and results[-1].latency_ms == pytest.approx(5.0)
    event = payloads.build(ts, "std_msgs/msg/String", 100, 3, T_NS)
    ev = codec.encode(event, "std_msgs/msg/String", "/robot1/events", no_drop=True, seq=10)
    assert rec.feed(ev, T_NS + 1) is not None
    assert rec.feed(ev, T_NS + 2) is None  # a resend after a reconnect
    assert rec.duplicates == 1
    assert rec.feed(b"garbage", T_NS) is None and rec.errors == 1
    got = list(load(out.getvalue()))
    assert [(s.topic, s.seq) for s in got] == [("/robot1/img", 7), ("/robot1/events", 3)]


def test_client_configs_of_profiles_and_baselines() -> None:
    p = profiles.profile("dropout")
    cfg = profiles.client_config(p, "ws://1.2.3.4:8080/")
    assert [e["no_drop"] for e in cfg["publish"]] == [False, False, False, True, False]
    camera = cfg["publish"][-1]
    assert camera["video"] == {"codec": "h264", "max_bitrate_kbps": 600}
    assert "video" not in cfg["publish"][0]
    base = profiles.client_config(profiles.all_no_drop(p), "ws://x:1/")
    assert all(e["no_drop"] for e in base["publish"])
    rf = profiles.robofleet_like(profiles.profile("priority"))
    assert {t.priority for t in rf.topics} == {1.0}
    assert rf.max_fragment_bytes >= 65_536 * 2
    assert profiles.client_config(rf, "ws://x:1/")["limits"]["scheduler"] == "robofleet"
    json.dumps(cfg)
    with pytest.raises(FleetError, match="unknown load profile"):
        profiles.profile("nope")


def test_client_config_is_valid_for_the_client() -> None:
    from fleetctl.client.config import parse_client_config

    for name, p in profiles.PROFILES.items():
        parsed = parse_client_config(profiles.client_config(p, "ws://10.0.0.1:8080/"),
                                     source=name)
        assert [s.remote_topic for s in parsed.publish] == [t.remote_topic for t in p.topics]
