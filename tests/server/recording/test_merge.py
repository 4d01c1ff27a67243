"""merge(): recordings written by the relay's own RecordingWriter, merged into one file."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from fleetctl.errors import FleetError
from fleetctl.server.recording import carry, files
from fleetctl.server.recording.config import RecordingConfig
from fleetctl.server.recording.merge import (
    MergeCounts,
    MergeSource,
    Selection,
    _indexed,
    _lanes,
    merge,
)
from fleetctl.server.recording.writer import RecordingWriter
from fleetctl.wire.codec import default_codec
from tests.server.recording.damaged import damaged_recording
from tests.support import ManualClock

STRING = "std_msgs/msg/String"
VIDEO = "foxglove_msgs/msg/CompressedVideo"
T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def frame(topic: str, text: str, at_ms: int, *, seq: int = 0, latched: bool = False) -> bytes:
    """A String frame published *at_ms* after T0."""
    codec = default_codec()
    return codec.encode(codec.registry.get(STRING).cls(text), STRING, topic,
                        publish_time_ns=T0 + at_ms * MS, seq=seq or at_ms, latched=latched)


class Replica:
    """One replica's recorder (RecordingWriter, injected clocks) in its own directory."""

    def __init__(self, directory: Path, label: str, **config: object) -> None:
        self.clock = ManualClock(1_000.0)
        cfg = RecordingConfig(directory, (), file_label=label,  # type: ignore[arg-type]
                              **config)
        self.writer = RecordingWriter(cfg, default_codec(), 1 << 20, clock=self.clock,
                                      wall_clock_s=lambda: 1_764_000_000.0 + self.clock.now_s)
        self.writer.start()
        self.directory = directory

    def record(self, *frames: bytes) -> None:
        for f in frames:
            self.writer.record(1, f, 0, self.clock.now_s)

    def files(self) -> list[MergeSource]:
        return [MergeSource(f.path, f.name) for f in files.scan(self.directory)]


def run(tmp_path: Path, sources: list[MergeSource],
        selection: Selection | None = None) -> tuple[Path, MergeCounts]:
    target = tmp_path / "merged.mcap"
    scratch = tmp_path / "scratch"
    scratch.mkdir(exist_ok=True)
    with target.open("xb") as out:
        counts = merge(sources, out, selection or Selection(), scratch)
    return target, counts


def read(path: Path) -> Iterator[tuple[str, int, str]]:
    """(topic, log time in ms after T0, text) of every message, in file order, decoded
    by rosbags (which needs the summary and the schemas)."""
    with AnyReader([path]) as reader:
        for connection, log_time, raw in reader.messages():
            text = reader.deserialize(raw, connection.msgtype).data
            yield connection.topic, (log_time - T0) // MS, text


def test_messages_come_in_log_time_order_across_replicas_and_arrival(
        tmp_path: Path) -> None:
    a, b = Replica(tmp_path / "a", "relay-a"), Replica(tmp_path / "b", "relay-b")
    # Arrival order is not log-time order (two topics of a robot, a late frame).
    a.record(frame("/husky1/chat", "a30", 30), frame("/husky1/odom", "a10", 10),
             frame("/husky1/chat", "a50", 50))
    b.record(frame("/husky1/chat", "b40", 40), frame("/husky1/chat", "b20", 20),
             frame("/husky1/odom", "b60", 60))
    a.writer.close()
    b.writer.close()
    target, counts = run(tmp_path, a.files() + b.files())
    assert [(t, ms) for t, ms, _ in read(target)] == [
        ("/husky1/odom", 10), ("/husky1/chat", 20), ("/husky1/chat", 30),
        ("/husky1/chat", 40), ("/husky1/chat", 50), ("/husky1/odom", 60)]
    assert (counts.messages, counts.start_ns, counts.end_ns) == (6, T0 + 10 * MS, T0 + 60 * MS)
    assert counts.topics == ["/husky1/chat", "/husky1/odom"]
    with target.open("rb") as stream:  # indexed, one channel per topic and one schema
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.chunk_indexes and summary.statistics.message_count == 6
    assert sorted(c.topic for c in summary.channels.values()) == ["/husky1/chat",
                                                                  "/husky1/odom"]
    assert [s.name for s in summary.schemas.values()] == [STRING]
    assert counts.channels == 2


def test_the_same_topic_with_another_type_definition_is_a_channel_of_its_own(
        tmp_path: Path) -> None:
    a = Replica(tmp_path / "a", "relay-a")
    a.record(frame("/husky1/chat", "one", 1))
    a.writer.close()
    other = tmp_path / "other.mcap"  # the same topic and type name, another definition
    from mcap.writer import Writer

    with other.open("wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="test")
        schema = w.register_schema(STRING, "ros2msg", b"string data\nint32 extra")
        channel = w.register_channel("/husky1/chat", "cdr", schema)
        w.add_message(channel, T0 + 2 * MS, b"\x00\x01\x00\x00\x01\x00\x00\x00\x00\x00\x00",
                      T0 + 2 * MS)
        w.finish()
    _target, counts = run(tmp_path, [*a.files(), MergeSource(other, "other.mcap")])
    assert counts.messages == 2 and counts.channels == 2 and counts.topics == ["/husky1/chat"]


def test_robot_and_time_window_select_topics_and_log_times(tmp_path: Path) -> None:
    a = Replica(tmp_path / "a", "relay-a")
    a.record(*(frame(f"/{robot}/chat", f"{robot}{ms}", ms)
               for ms in range(0, 100, 10) for robot in ("husky1", "husky2")),
             frame("/status", "fleet", 55))
    a.writer.close()
    selection = Selection("husky1", T0 + 20 * MS, T0 + 60 * MS)  # inclusive bounds
    target, counts = run(tmp_path, a.files(), selection)
    assert [(t, ms) for t, ms, _ in read(target)] == [("/husky1/chat", ms)
                                                      for ms in (20, 30, 40, 50, 60)]
    assert counts.topics == ["/husky1/chat"]


def test_a_frame_recorded_by_two_replicas_is_written_once(tmp_path: Path) -> None:
    """A robot that fails over sends again what its old replica had not acknowledged:
    both replicas recorded it (same publish time, sequence and data)."""
    a, b = Replica(tmp_path / "a", "relay-a"), Replica(tmp_path / "b", "relay-b")
    a.record(frame("/husky1/chat", "one", 10), frame("/husky1/chat", "two", 20))
    b.record(frame("/husky1/chat", "two", 20), frame("/husky1/chat", "three", 30))
    # Not a duplicate: another sequence number at the same time, or other data.
    b.record(frame("/husky1/chat", "two", 20, seq=99), frame("/husky1/chat", "2", 20))
    a.writer.close()
    b.writer.close()
    target, counts = run(tmp_path, a.files() + b.files())
    assert [text for _, _, text in read(target)] == ["one", "two", "two", "2", "three"]
    assert (counts.messages, counts.duplicates, counts.repeats) == (5, 1, 0)


def _rotated_with_a_map(tmp_path: Path) -> Replica:
    """Replica relay-a's closed recording in three rotated files: a latched map at 5 ms and
    a chat at 10 ms in the first, a chat at 20 s and at 40 s in the next two (each of which
    starts with its copy of the map)."""
    a = Replica(tmp_path / "a", "relay-a", max_file_duration_s=10.0)
    a.record(frame("/husky1/map", "map", 5, latched=True), frame("/husky1/chat", "x", 10))
    for ms in (20_000, 40_000):
        a.clock.now_s += 11
        a.record(frame("/husky1/chat", "y", ms))
    a.writer.close()
    return a


def test_rotated_files_give_the_latched_map_once(tmp_path: Path) -> None:
    """Every rotated file starts with a copy of the latched map (log time: the file's
    start); merged, the run has it once, at its original time."""
    a = _rotated_with_a_map(tmp_path)
    parts = a.files()
    assert len(parts) == 3
    target, counts = run(tmp_path, parts)
    got = [(t, ms) for t, ms, _ in read(target)]
    assert got == [("/husky1/map", 5), ("/husky1/chat", 10), ("/husky1/chat", 20_000),
                   ("/husky1/chat", 40_000)]
    assert (counts.repeats, counts.duplicates) == (2, 0)
    (tmp_path / "merged.mcap").unlink()
    # The last file alone: its copy is the map (there is no original to repeat).
    target, counts = run(tmp_path, parts[-1:])
    assert [(t, ms) for t, ms, _ in read(target)] == [("/husky1/map", 40_000),
                                                      ("/husky1/chat", 40_000)]
    assert counts.repeats == 0


def test_an_open_file_is_read_up_to_its_last_flush(tmp_path: Path) -> None:
    a = Replica(tmp_path / "a", "relay-a", flush_interval_s=1.0)
    a.record(frame("/husky1/chat", "flushed", 10))
    a.clock.now_s += 2
    a.writer.tick()  # the chunk is on disk
    a.record(frame("/husky1/chat", "in memory", 20))
    [source] = a.files()
    assert not files.is_complete(source.path)
    target, counts = run(tmp_path, [source])
    assert [text for _, _, text in read(target)] == ["flushed"]
    assert counts.still_open == [source.label]
    a.writer.close()


def test_a_cut_short_file_is_read_up_to_its_last_complete_record(tmp_path: Path) -> None:
    a = Replica(tmp_path / "a", "relay-a", chunk_bytes=256)
    a.record(*(frame("/husky1/chat", "x" * 100, ms) for ms in range(1, 41)))
    a.writer.close()
    [source] = a.files()
    data = source.path.read_bytes()
    source.path.write_bytes(data[:len(data) // 2])
    _target, counts = run(tmp_path, [source])
    assert 0 < counts.messages < 40 and counts.still_open == [source.label]


@pytest.mark.parametrize("content", [None, b"", b"not mcap", b"just some text, no MCAP " * 9])
def test_a_missing_or_foreign_file_is_named(tmp_path: Path, content: bytes | None) -> None:
    path = tmp_path / "in.mcap"
    if content is not None:
        path.write_bytes(content)
    if content == b"":  # an empty file: the server has just created it, nothing yet
        _target, counts = run(tmp_path, [MergeSource(path, "the label")])
        assert counts.messages == 0
        return
    with pytest.raises(FleetError, match=r"^the label: (no such file|not an MCAP file)"):
        run(tmp_path, [MergeSource(path, "the label")])


def test_a_damaged_chunk_is_named(tmp_path: Path) -> None:
    path = tmp_path / "damaged.mcap"
    damaged_recording(path)
    with pytest.raises(FleetError, match=r"^the label: damaged data"):
        run(tmp_path, [MergeSource(path, "the label")])


def test_no_input_is_an_empty_file(tmp_path: Path) -> None:
    target, counts = run(tmp_path, [])
    with target.open("rb") as stream:
        assert list(make_reader(stream).iter_messages()) == []
    assert counts.messages == 0


def test_files_that_follow_each_other_are_read_one_after_another(tmp_path: Path) -> None:
    """A week of hourly files per replica: as many files open at once as overlap in time
    (one per replica), not one per file (the file descriptors, the chunks in memory)."""
    a = Replica(tmp_path / "a", "relay-a", max_file_duration_s=10.0)
    b = Replica(tmp_path / "b", "relay-b", max_file_duration_s=10.0)
    for hour in range(4):
        a.record(frame("/husky1/chat", f"a{hour}", hour * 1000), frame(
            "/husky1/chat", f"a{hour}", hour * 1000 + 500))
        b.record(frame("/husky2/chat", f"b{hour}", hour * 1000 + 250), frame(
            "/husky2/chat", f"b{hour}", hour * 1000 + 1000))  # ends as a's next begins
        a.clock.now_s += 11
        b.clock.now_s += 11
    a.writer.close()
    b.writer.close()
    counts = MergeCounts()
    inputs = [_indexed(s, tmp_path, n, counts) for n, s in enumerate(a.files() + b.files())]
    lanes = _lanes(inputs)
    assert sorted(len(lane) for lane in lanes) == [4, 4]
    assert all(sorted(lane, key=lambda i: i.start_ns) == lane for lane in lanes)
    target, counts = run(tmp_path, a.files() + b.files())
    times = [ms for _, ms, _ in read(target)]
    assert times == sorted(times) and counts.messages == 16


def read_times(path: Path) -> list[tuple[str, int, int, str]]:
    """(topic, log time and publish time in ms after T0, text) of every String message,
    in file order."""
    store = default_codec().registry.typestore
    with path.open("rb") as stream:
        return [(c.topic, (m.log_time - T0) // MS, (m.publish_time - T0) // MS,
                 store.deserialize_cdr(m.data, STRING).data)
                for s, c, m in make_reader(stream).iter_messages(log_time_order=False)
                if s is not None and s.name == STRING]


def test_since_carries_the_newest_latched_message_of_each_channel_to_the_window_start(
        tmp_path: Path) -> None:
    """A map sent once at the start is what a window of the incident needs to be read;
    as a rotated file starts with copies of the latched messages, the merged window
    starts with the newest of each (log time: the window start, publish time: the
    original's)."""
    a = Replica(tmp_path / "a", "relay-a")
    a.record(*(frame("/husky1/map", f"map v{v}", v, latched=True) for v in range(1, 51)),
             frame("/husky1/tf_static", "static", 55, latched=True),
             frame("/husky2/map", "husky2's map", 57, latched=True),
             frame("/husky1/chat", "before", 60),  # not latched: not carried
             frame("/husky1/chat", "in the window", 200))
    a.writer.close()
    target, counts = run(tmp_path, a.files(), Selection(since_ns=T0 + 100 * MS))
    assert read_times(target) == [
        ("/husky1/map", 100, 50, "map v50"), ("/husky1/tf_static", 100, 55, "static"),
        ("/husky2/map", 100, 57, "husky2's map"), ("/husky1/chat", 200, 200, "in the window")]
    assert (counts.messages, counts.carried, counts.start_ns) == (4, 3, T0 + 100 * MS)
    (tmp_path / "merged.mcap").unlink()
    target, counts = run(tmp_path, a.files(), Selection("husky1", since_ns=T0 + 100 * MS))
    assert [(t, ms, text) for t, ms, _, text in read_times(target)] == [
        ("/husky1/map", 100, "map v50"), ("/husky1/tf_static", 100, "static"),
        ("/husky1/chat", 200, "in the window")]
    assert counts.carried == 2


def test_a_carried_message_makes_the_next_start_of_file_copy_a_repeat(
        tmp_path: Path) -> None:
    """Rotated files each start with a copy of the map: the newest before the window
    (here a copy itself) is carried, the one in the window is left out as a repeat."""
    a = _rotated_with_a_map(tmp_path)
    target, counts = run(tmp_path, a.files(), Selection(since_ns=T0 + 30_000 * MS))
    assert read_times(target) == [("/husky1/map", 30_000, 5, "map"),
                                  ("/husky1/chat", 40_000, 40_000, "y")]
    assert (counts.carried, counts.repeats) == (1, 1)


def test_the_newest_before_the_window_is_taken_across_inputs(tmp_path: Path) -> None:
    a, b = Replica(tmp_path / "a", "relay-a"), Replica(tmp_path / "b", "relay-b")
    a.record(frame("/husky1/map", "old", 10, latched=True),
             frame("/husky1/chat", "a", 150))
    b.record(frame("/husky1/map", "new", 20, latched=True),
             frame("/husky1/map", "in the window", 120, latched=True))
    a.writer.close()
    b.writer.close()
    target, counts = run(tmp_path, a.files() + b.files(), Selection(since_ns=T0 + 100 * MS))
    assert [(ms, text) for _, ms, _, text in read_times(target)] == [
        (100, "new"), (120, "in the window"), (150, "a")]
    assert counts.carried == 1


def video(at_ms: int, key: bool, pad: int = 0) -> bytes:
    """A CompressedVideo frame (H.264: SPS + IDR slice, or a non-IDR slice)."""
    codec = default_codec()
    store = codec.registry.typestore
    data = (b"\x00\x00\x00\x01\x67\x42\x00\x1e\x00\x00\x00\x01\x65\x88\x84" if key
            else b"\x00\x00\x00\x01\x41\x9a\x02") + b"\x00" * pad
    msg = store.types[VIDEO](
        timestamp=store.types["builtin_interfaces/msg/Time"](sec=at_ms, nanosec=0),
        frame_id="camera", format="h264", data=np.frombuffer(data, dtype=np.uint8))
    return codec.encode(msg, VIDEO, "/husky1/camera", publish_time_ns=T0 + at_ms * MS,
                        seq=at_ms)


def camera(path: Path) -> list[tuple[int, int]]:
    """(log time, publish time) in ms after T0 of each camera frame."""
    with path.open("rb") as stream:
        return [((m.log_time - T0) // MS, (m.publish_time - T0) // MS)
                for _s, c, m in make_reader(stream).iter_messages() if c.topic ==
                "/husky1/camera"]


def test_since_carries_the_video_since_its_last_keyframe(tmp_path: Path) -> None:
    """A window that starts between two keyframes could not show the camera until the
    next one: it starts with the frames from the last keyframe, as a rotated file does."""
    a = Replica(tmp_path / "a", "relay-a")
    a.record(*(video(ms, key) for ms, key in ((10, True), (20, False), (30, True),
                                               (40, False), (50, False), (60, False),
                                               (70, True))))
    a.writer.close()
    target, counts = run(tmp_path, a.files(), Selection(since_ns=T0 + 55 * MS))
    assert camera(target) == [(55, 30), (55, 40), (55, 50), (60, 60), (70, 70)]
    assert (counts.carried, counts.not_carried) == (3, [])


def test_a_video_group_past_the_bound_is_not_carried_and_said(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(carry, "MAX_GROUP_BYTES", 4096)
    a = Replica(tmp_path / "a", "relay-a")
    a.record(video(10, True), *(video(ms, False, pad=1000) for ms in range(20, 70, 10)))
    a.writer.close()
    target, counts = run(tmp_path, a.files(), Selection(since_ns=T0 + 65 * MS))
    assert camera(target) == []
    assert (counts.carried, counts.not_carried) == (0, ["/husky1/camera"])


def test_a_window_decodes_a_real_camera_from_its_first_frame(tmp_path: Path) -> None:
    pytest.importorskip("av")
    from fleetctl.client.video import VideoDecoder, VideoEncoder

    encoder = VideoEncoder("h264", 64, 48, fps=10.0, keyframe_interval_s=1.0)
    codec, rng = default_codec(), np.random.default_rng(7)
    store = codec.registry.typestore
    a = Replica(tmp_path / "a", "relay-a")
    for i in range(20):  # keyframes at 0 and 1 s: the window starts half a second after
        (encoded,) = encoder.encode(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8),
                                    i / 10.0)
        msg = store.types[VIDEO](
            timestamp=store.types["builtin_interfaces/msg/Time"](sec=i, nanosec=0),
            frame_id="camera", format="h264",
            data=np.frombuffer(encoded.data, dtype=np.uint8))
        a.record(codec.encode(msg, VIDEO, "/husky1/camera", seq=i + 1,
                              publish_time_ns=T0 + i * 100 * MS))
    a.writer.close()
    target, counts = run(tmp_path, a.files(), Selection(since_ns=T0 + 1500 * MS))
    decoder = VideoDecoder("h264")
    with target.open("rb") as stream:
        shown = [decoder.decode(store.deserialize_cdr(m.data, VIDEO).data.tobytes(),
                                m.sequence) is not None
                 for _s, _c, m in make_reader(stream).iter_messages()]
    # The group from the 1 s keyframe (frames 10-14), then the window's: every one
    # decodes, the first included.
    assert len(shown) == 5 + 5 and all(shown), shown
    assert counts.carried == 5
