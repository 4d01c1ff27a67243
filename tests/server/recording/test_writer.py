"""RecordingWriter alone (no server): rotation, bounds and drops with injected clocks."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from fleetctl.server.recording import files
from fleetctl.server.recording.config import RecordingConfig
from fleetctl.server.recording.writer import RecordingWriter
from fleetctl.wire import fragments, samples
from fleetctl.wire.codec import default_codec
from tests.support import ManualClock

STRING = "std_msgs/msg/String"


def frame(text: str, seq: int, topic: str = "/r/chat") -> bytes:
    codec = default_codec()
    return codec.encode(codec.registry.get(STRING).cls(text), STRING, topic,
                        publish_time_ns=1_700_000_000_000_000_000 + seq, seq=seq)


def writer(tmp_path: Path, clock: ManualClock, **kw: object) -> RecordingWriter:
    config = RecordingConfig(tmp_path, (), **kw)  # type: ignore[arg-type]
    out = RecordingWriter(config, default_codec(), 1 << 20, clock=clock,
                          wall_clock_s=lambda: 1_764_000_000.0 + clock.now_s)
    out.start()
    return out


def test_rotates_by_duration_and_closes_complete_files(tmp_path: Path) -> None:
    clock = ManualClock(1_000.0)
    w = writer(tmp_path, clock, max_file_duration_s=10.0)
    w.record(1, frame("a", 1), 0, clock.now_s)
    clock.now_s += 11
    w.record(1, frame("b", 2), 0, clock.now_s)  # past the duration: a new file first
    w.close()
    found = files.scan(tmp_path)
    assert len(found) == 2 and all(files.is_complete(f.path) for f in found)
    assert [files.describe(f.path)["messages"] for f in found] == [1, 1]


def test_rotates_by_size_and_drops_what_can_never_fit(tmp_path: Path) -> None:
    clock = ManualClock(1_000.0)
    w = writer(tmp_path, clock, max_file_bytes=4096, max_total_bytes=1 << 20, chunk_bytes=512)
    for i in range(40):
        w.record(1, frame("x" * 200, i + 1), 0, clock.now_s)
    w.record(1, frame("y" * 5000, 99), 0, clock.now_s)
    w.close()
    found = files.scan(tmp_path)
    assert len(found) >= 2
    assert all(f.size_bytes <= 4096 for f in found)
    assert sum(files.describe(f.path)["messages"] for f in found) == 40
    assert w.stats.dropped["too_big"] == 1 and w.stats.messages == 40


def test_malformed_frames_are_counted_not_fatal(tmp_path: Path) -> None:
    clock = ManualClock(1_000.0)
    w = writer(tmp_path, clock)
    w.record(1, b"\x01" * 40, 0, clock.now_s)
    w.record(1, frame("ok", 1), 0, clock.now_s)
    w.close()
    assert w.stats.dropped["malformed"] == 1 and w.stats.messages == 1


def test_a_frame_without_publish_time_gets_the_receive_time(tmp_path: Path) -> None:
    clock = ManualClock(1_000.0)
    w = writer(tmp_path, clock)
    codec = default_codec()
    plain = codec.encode(codec.registry.get(STRING).cls("t"), STRING, "/r/chat")
    w.record(1, plain, 123_456_789, clock.now_s)
    w.close()
    [(_, _, message)] = list(files.read_messages(files.scan(tmp_path)[0].path))
    assert message.log_time == message.publish_time == 123_456_789


def test_fragments_of_messages_that_never_complete_are_counted(tmp_path: Path) -> None:
    clock = ManualClock(1_000.0)
    w = writer(tmp_path, clock)
    codec = default_codec()
    cloud = samples.point_cloud(codec.registry, 2, 512)
    whole = codec.encode(cloud, "sensor_msgs/msg/PointCloud2", "/r/cloud", seq=1)
    first, second = (fragments.split(whole, topic="/r/cloud", message_id=m,
                                     max_fragment_bytes=4096, no_drop=False)
                     for m in (1, 2))
    w.record(1, first[0], 0, clock.now_s)  # message 1 starts...
    for part in second:  # ...and message 2 supersedes it
        w.record(1, part, 0, clock.now_s)
    w.close()
    snap = w.stats.snapshot()
    assert snap["dropped"]["incomplete"] == 1 and snap["messages"] == 1


def latched_frame(text: str, seq: int, topic: str) -> bytes:
    codec = default_codec()
    return codec.encode(codec.registry.get(STRING).cls(text), STRING, topic, latched=True,
                        publish_time_ns=1_700_000_000_000_000_000 + seq, seq=seq)


def test_every_new_file_starts_with_the_latched_topics(tmp_path: Path) -> None:
    """A rotated file had no map and no /tf_static (published once, at the robot's start):
    opened or replayed alone it showed no map and a TF tree without its static frames."""
    clock = ManualClock(1_000.0)
    w = writer(tmp_path, clock, max_file_duration_s=10.0)
    w.record(1, latched_frame("the map", 1, "/r/map"), 0, clock.now_s)
    w.record(1, latched_frame("static tf", 2, "/r/tf_static"), 0, clock.now_s)
    w.record(1, frame("a", 3), 0, clock.now_s)
    clock.now_s += 11
    w.record(1, frame("b", 4), 0, clock.now_s)  # a new file: the map and static TF first
    clock.now_s += 11
    w.record(1, latched_frame("map v2", 5, "/r/map"), 0, clock.now_s)  # new file, new map
    w.close()
    found = files.scan(tmp_path)
    assert len(found) == 3
    contents = [[(ch.topic, bytes(m.data), m.log_time, m.publish_time)
                 for _s, ch, m in files.read_messages(f.path)] for f in found]
    codec = default_codec()

    def cdr(text: str) -> bytes:
        return bytes(codec.registry.typestore.serialize_cdr(
            codec.registry.get(STRING).cls(text), STRING))

    t0 = 1_700_000_000_000_000_000
    assert [c[:2] for c in contents[1]] == [
        ("/r/map", cdr("the map")), ("/r/tf_static", cdr("static tf")), ("/r/chat", cdr("b"))]
    # The copies are logged when the file starts (a player does not open the file hours
    # before its data) and keep their original publish time.
    assert [c[2:] for c in contents[1]] == [(t0 + 4, t0 + 1), (t0 + 4, t0 + 2), (t0 + 4,) * 2]
    # A file opened by a latched message holds its new value once, not the old one too.
    assert [c[:2] for c in contents[2]] == [
        ("/r/tf_static", cdr("static tf")), ("/r/map", cdr("map v2"))]
    with (found[1].path).open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    qos = {ch.topic: ch.metadata["offered_qos_profiles"] for ch in summary.channels.values()}
    assert "transient_local" in qos["/r/map"] and "volatile" in qos["/r/chat"]


def test_latched_copies_stay_within_a_quarter_of_a_file(tmp_path: Path) -> None:
    clock = ManualClock(1_000.0)
    w = writer(tmp_path, clock, max_file_duration_s=10.0, max_file_bytes=8192,
               max_total_bytes=1 << 20, chunk_bytes=512)
    w.record(1, latched_frame("m" * 3000, 1, "/r/map"), 0, clock.now_s)  # > 8192 / 4
    w.record(1, latched_frame("s" * 100, 2, "/r/tf_static"), 0, clock.now_s)
    clock.now_s += 11
    w.record(1, frame("b", 3), 0, clock.now_s)
    w.close()
    second = files.scan(tmp_path)[1]
    assert [ch.topic for _s, ch, _m in files.read_messages(second.path)] == [
        "/r/tf_static", "/r/chat"]


VIDEO = "foxglove_msgs/msg/CompressedVideo"
# H.264 Annex B access units: SPS + IDR slice (a keyframe), one non-IDR slice (a delta).
KEY_H264 = b"\x00\x00\x00\x01\x67\x42\x00\x1e" + b"\x00\x00\x00\x01\x65\x88\x84"
DELTA_H264 = b"\x00\x00\x00\x01\x41\x9a\x02"


def video_frame(seq: int, key: bool, pad: int = 0, topic: str = "/r/camera") -> bytes:
    codec = default_codec()
    store = codec.registry.typestore
    msg = store.types[VIDEO](
        timestamp=store.types["builtin_interfaces/msg/Time"](sec=seq, nanosec=0),
        frame_id="camera", format="h264",
        data=np.frombuffer((KEY_H264 if key else DELTA_H264) + b"\x00" * pad, dtype=np.uint8))
    return codec.encode(msg, VIDEO, topic, publish_time_ns=1_700_000_000_000_000_000 + seq,
                        seq=seq)


def _video_seqs(path: Path) -> list[tuple[int, int, int]]:
    """(sequence, log time offset, publish time offset) of each video message, in order."""
    t0 = 1_700_000_000_000_000_000
    return [(m.sequence, m.log_time - t0, m.publish_time - t0)
            for _s, ch, m in files.read_messages(path) if ch.topic == "/r/camera"]


def test_every_new_file_starts_with_the_video_since_its_last_keyframe(tmp_path: Path) -> None:
    """A file that started between two keyframes could not show the camera until the
    next one (2 s by default): every frame before it needed frames of the old file."""
    clock = ManualClock(1_000.0)
    w = writer(tmp_path, clock, max_file_duration_s=10.0)
    for seq, key in ((1, True), (2, False), (3, True), (4, False), (5, False)):
        w.record(1, video_frame(seq, key), 0, clock.now_s)
    clock.now_s += 11
    w.record(1, video_frame(6, False), 0, clock.now_s)  # a new file, opened by a delta frame
    w.record(1, video_frame(7, False), 0, clock.now_s)
    clock.now_s += 11
    w.record(1, video_frame(8, True), 0, clock.now_s)  # a new file, opened by a keyframe
    w.close()
    first, second, third = files.scan(tmp_path)
    assert [s for s, _, _ in _video_seqs(first.path)] == [1, 2, 3, 4, 5]
    # The group from keyframe 3, logged when the file starts, with its publish times.
    assert _video_seqs(second.path) == [(3, 6, 3), (4, 6, 4), (5, 6, 5), (6, 6, 6),
                                        (7, 7, 7)]
    # Opened by a keyframe: the old group would only come before it, undecodable to none.
    assert _video_seqs(third.path) == [(8, 8, 8)]


def test_video_copies_stay_within_a_quarter_of_a_file(tmp_path: Path) -> None:
    clock = ManualClock(1_000.0)
    w = writer(tmp_path, clock, max_file_duration_s=10.0, max_file_bytes=16384,
               max_total_bytes=1 << 20, chunk_bytes=512)
    w.record(1, video_frame(1, True, pad=3000), 0, clock.now_s)
    w.record(1, video_frame(2, False, pad=3000), 0, clock.now_s)  # 6 KB > 16384 / 4
    w.record(1, video_frame(3, False), 0, clock.now_s)
    clock.now_s += 11
    w.record(1, video_frame(4, False), 0, clock.now_s)
    w.record(1, video_frame(5, True), 0, clock.now_s)
    clock.now_s += 11
    w.record(1, video_frame(6, False), 0, clock.now_s)
    w.close()
    _, second, third = files.scan(tmp_path)
    # The group outgrew its share: dropped until the next keyframe, kept again from it.
    assert [s for s, _, _ in _video_seqs(second.path)] == [4, 5]
    assert [s for s, _, _ in _video_seqs(third.path)] == [5, 6]


def test_a_rotated_file_decodes_a_real_camera_from_its_first_frame(tmp_path: Path) -> None:
    av = pytest.importorskip("av")
    del av
    from fleetctl.client.video import VideoDecoder, VideoEncoder

    encoder = VideoEncoder("h264", 64, 48, fps=10.0, keyframe_interval_s=1.0)
    clock = ManualClock(1_000.0)
    w = writer(tmp_path, clock, max_file_duration_s=10.0)
    codec, rng = default_codec(), np.random.default_rng(7)
    store = codec.registry.typestore
    for i in range(20):  # keyframes at 0 and 1 s: the rotation comes half a second after
        if i == 15:
            clock.now_s += 11
        image = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
        (encoded,) = encoder.encode(image, i / 10.0)
        msg = store.types[VIDEO](
            timestamp=store.types["builtin_interfaces/msg/Time"](sec=i, nanosec=0),
            frame_id="camera", format="h264",
            data=np.frombuffer(encoded.data, dtype=np.uint8))
        w.record(1, codec.encode(msg, VIDEO, "/r/camera", seq=i + 1,
                                 publish_time_ns=1_700_000_000_000_000_000 + i), 0, clock.now_s)
    w.close()
    second = files.scan(tmp_path)[1]
    decoder = VideoDecoder("h264")
    shown = []
    for _schema, _channel, record in files.read_messages(second.path):
        video = store.deserialize_cdr(bytes(record.data), VIDEO)
        shown.append(decoder.decode(video.data.tobytes(), record.sequence) is not None)
    # The group from the 1 s keyframe (frames 10-14 of the old file), then the new frames:
    # every one decodes, the first included.
    assert len(shown) == 5 + 5 and all(shown), shown


def rotating_writer(tmp_path: Path, clock: ManualClock, wall_offset_s: list[float],
                    ) -> RecordingWriter:
    """A writer whose byte bound deletes a file at about every second rotation; its wall
    clock is the real one (the files' mtimes are real) plus ``wall_offset_s[0]``."""
    config = RecordingConfig(tmp_path, (), max_file_bytes=4096, max_total_bytes=8192,
                             chunk_bytes=512)
    out = RecordingWriter(config, default_codec(), 1 << 20, clock=clock,
                          wall_clock_s=lambda: time.time() + wall_offset_s[0])
    out.start()
    return out


def fill(w: RecordingWriter, clock: ManualClock, first_seq: int, n: int = 40) -> None:
    for i in range(n):
        w.record(1, frame("x" * 200, first_seq + i), 0, clock.now_s)


def test_deleting_for_the_bounds_is_info_and_counted(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    clock = ManualClock(1_000.0)
    w = rotating_writer(tmp_path, clock, [2 * 3600.0])  # the files hold hours: no warning
    with caplog.at_level(logging.INFO, "fleetctl.server.recording"):
        fill(w, clock, 1)
    deletions = [r for r in caplog.records if "deleted" in r.getMessage()]
    assert deletions and all(r.levelno == logging.INFO for r in deletions)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert w.stats.deleted_files["max_total_bytes"] == len(deletions)
    assert w.stats.deleted_bytes["max_total_bytes"] > 0


def test_a_budget_holding_minutes_warns_once_an_hour_saying_what_to_change(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    clock = ManualClock(1_000.0)
    w = rotating_writer(tmp_path, clock, [0.0])
    with caplog.at_level(logging.INFO, "fleetctl.server.recording"):
        fill(w, clock, 1)
        clock.now_s += 3599  # within the hour: still one line
        fill(w, clock, 100)
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, warnings
    assert "max_total_bytes (8192 bytes) holds only" in warnings[0]
    assert "raise recording.max_total_bytes" in warnings[0]
    assert w.stats.deleted_files["max_total_bytes"] >= 4
    caplog.clear()
    with caplog.at_level(logging.INFO, "fleetctl.server.recording"):
        clock.now_s += 2  # an hour after the first line
        fill(w, clock, 200)
    assert len([r for r in caplog.records if r.levelno >= logging.WARNING]) == 1
