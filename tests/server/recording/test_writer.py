"""RecordingWriter alone (no server): rotation, bounds and drops with injected clocks."""

from __future__ import annotations

from pathlib import Path

from fleetctl.server.recording import files
from fleetctl.server.recording.config import RecordingConfig
from fleetctl.server.recording.writer import RecordingWriter
from fleetctl.wire import fragments, samples
from fleetctl.wire.codec import default_codec

STRING = "std_msgs/msg/String"


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def frame(text: str, seq: int, topic: str = "/r/chat") -> bytes:
    codec = default_codec()
    return codec.encode(codec.registry.get(STRING).cls(text), STRING, topic,
                        publish_time_ns=1_700_000_000_000_000_000 + seq, seq=seq)


def writer(tmp_path: Path, clock: Clock, **kw: object) -> RecordingWriter:
    config = RecordingConfig(tmp_path, (), **kw)  # type: ignore[arg-type]
    out = RecordingWriter(config, default_codec(), 1 << 20, clock=clock,
                          wall_clock_s=lambda: 1_764_000_000.0 + clock.now)
    out.start()
    return out


def test_rotates_by_duration_and_closes_complete_files(tmp_path: Path) -> None:
    clock = Clock()
    w = writer(tmp_path, clock, max_file_duration_s=10.0)
    w.record(1, frame("a", 1), 0, clock.now)
    clock.now += 11
    w.record(1, frame("b", 2), 0, clock.now)  # past the duration: a new file first
    w.close()
    found = files.scan(tmp_path)
    assert len(found) == 2 and all(files.is_complete(f.path) for f in found)
    assert [files.describe(f.path)["messages"] for f in found] == [1, 1]


def test_rotates_by_size_and_drops_what_can_never_fit(tmp_path: Path) -> None:
    clock = Clock()
    w = writer(tmp_path, clock, max_file_bytes=4096, max_total_bytes=1 << 20, chunk_bytes=512)
    for i in range(40):
        w.record(1, frame("x" * 200, i + 1), 0, clock.now)
    w.record(1, frame("y" * 5000, 99), 0, clock.now)
    w.close()
    found = files.scan(tmp_path)
    assert len(found) >= 2
    assert all(f.size_bytes <= 4096 for f in found)
    assert sum(files.describe(f.path)["messages"] for f in found) == 40
    assert w.stats.dropped["too_big"] == 1 and w.stats.messages == 40


def test_malformed_frames_are_counted_not_fatal(tmp_path: Path) -> None:
    clock = Clock()
    w = writer(tmp_path, clock)
    w.record(1, b"\x01" * 40, 0, clock.now)
    w.record(1, frame("ok", 1), 0, clock.now)
    w.close()
    assert w.stats.dropped["malformed"] == 1 and w.stats.messages == 1


def test_a_frame_without_publish_time_gets_the_receive_time(tmp_path: Path) -> None:
    clock = Clock()
    w = writer(tmp_path, clock)
    codec = default_codec()
    plain = codec.encode(codec.registry.get(STRING).cls("t"), STRING, "/r/chat")
    w.record(1, plain, 123_456_789, clock.now)
    w.close()
    [(_, _, message)] = list(files.read_messages(files.scan(tmp_path)[0].path))
    assert message.log_time == message.publish_time == 123_456_789


def test_fragments_of_messages_that_never_complete_are_counted(tmp_path: Path) -> None:
    clock = Clock()
    w = writer(tmp_path, clock)
    codec = default_codec()
    cloud = samples.point_cloud(codec.registry, 2, 512)
    whole = codec.encode(cloud, "sensor_msgs/msg/PointCloud2", "/r/cloud", seq=1)
    first, second = (fragments.split(whole, topic="/r/cloud", message_id=m,
                                     max_fragment_bytes=4096, no_drop=False)
                     for m in (1, 2))
    w.record(1, first[0], 0, clock.now)  # message 1 starts...
    for part in second:  # ...and message 2 supersedes it
        w.record(1, part, 0, clock.now)
    w.close()
    snap = w.stats.snapshot()
    assert snap["dropped"]["incomplete"] == 1 and snap["messages"] == 1
