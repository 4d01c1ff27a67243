"""MCAP recording through a real relay and real WebSocket clients.

Every recorded file is read back twice, with rosbags' rosbag2 reader (AnyReader on the bare
.mcap) and with mcap's own reader, and compared with what the robot published.
"""

from __future__ import annotations

import logging
import os
import random
import signal
import stat
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from fleetctl.server.app import RelayServer
from fleetctl.server.msgtypes import codec_for
from fleetctl.server.permissions import PermissionsPool
from fleetctl.server.recording import files
from fleetctl.server.recording.config import RecordingConfig, RecordingRule
from fleetctl.server.recording.recorder import FLUSH_BYTES, FLUSH_DELAY_S, Recorder
from fleetctl.server.recording.worker import HEADER
from fleetctl.wire import fragments, samples
from fleetctl.wire.codec import default_codec
from fleetctl.wire.compression import CompressionCodec, compress
from tests.server.conftest import ALICE_TOKEN, client, wait_for
from tests.server.test_app import http_get

# Generous: every server starts a worker process, slow on a loaded machine.
DEADLINE_S = 30.0
ROBOT = "127.0.0.2"  # husky1 by address (tests/server/conftest.py)
STRING = "std_msgs/msg/String"


def recording(tmp_path: Path, **kw: Any) -> RecordingConfig:
    rules = kw.pop("rules", (RecordingRule("/husky1/.*", ("husky1",)),))
    return RecordingConfig(tmp_path / "rec", rules, **kw)


def published(n: int, topic: str = "/husky1/chat", start_ns: int = 1_700_000_000_000_000_000,
              ) -> list[tuple[str, str, Any, bytes]]:
    """*n* String messages as (topic, type, message, frame), publish times 1 ms apart."""
    codec = default_codec()
    cls = codec.registry.get(STRING).cls
    out = []
    for i in range(n):
        msg = cls(f"message {i}")
        frame = codec.encode(msg, STRING, topic, publish_time_ns=start_ns + i * 1_000_000,
                             seq=i + 1)
        out.append((topic, STRING, msg, frame))
    return out


def cdr(type_name: str, msg: Any) -> bytes:
    return bytes(default_codec().registry.typestore.serialize_cdr(msg, type_name))


def read_with_rosbags(path: Path) -> list[tuple[str, str, int, bytes]]:
    with AnyReader([path]) as reader:
        out = []
        for conn, timestamp, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)  # rosbags' own deserializer
            again = bytes(reader.typestore.serialize_cdr(msg, conn.msgtype))
            assert again == bytes(raw)
            out.append((conn.topic, conn.msgtype, timestamp, bytes(raw)))
        return out


def read_with_mcap(path: Path) -> list[tuple[str, str, int, bytes]]:
    with path.open("rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        out = []
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            assert schema is not None and schema.encoding == "ros2msg"
            assert channel.message_encoding == "cdr"
            assert message.publish_time == message.log_time
            out.append((channel.topic, schema.name, message.log_time, message.data))
        return out


def expected_rows(sent: list[tuple[str, str, Any, bytes]]) -> list[tuple[str, str, int, bytes]]:
    codec = default_codec()
    return [(topic, type_name, codec.decode(frame)[0].publish_time_ns, cdr(type_name, msg))
            for topic, type_name, msg, frame in sent]


def mixed_messages() -> list[tuple[str, str, Any, bytes]]:
    """Strings, a pose, a fragmented cloud and a compressed map, as a robot sends them."""
    codec, registry = default_codec(), default_codec().registry
    base = 1_700_000_100_000_000_000
    sent = published(20, start_ns=base)
    pose_cls = registry.get("geometry_msgs/msg/PoseStamped").cls
    pose = pose_cls(samples.header(registry, "map"),
                    registry.get("geometry_msgs/msg/Pose").cls(
                        registry.get("geometry_msgs/msg/Point").cls(1.0, 2.0, 3.0),
                        registry.get("geometry_msgs/msg/Quaternion").cls(0.0, 0.0, 0.0, 1.0)))
    t = base + 30_000_000
    sent.append(("/husky1/pose", "geometry_msgs/msg/PoseStamped", pose,
                 codec.encode(pose, "geometry_msgs/msg/PoseStamped", "/husky1/pose",
                              publish_time_ns=t, seq=1)))
    cloud = samples.point_cloud(registry, 4, 1024)
    sent.append(("/husky1/cloud", "sensor_msgs/msg/PointCloud2", cloud,
                 codec.encode(cloud, "sensor_msgs/msg/PointCloud2", "/husky1/cloud",
                              publish_time_ns=t + 1_000_000, seq=1)))
    grid = samples.occupancy_grid(registry)
    sent.append(("/husky1/map", "nav_msgs/msg/OccupancyGrid", grid,
                 codec.encode(grid, "nav_msgs/msg/OccupancyGrid", "/husky1/map",
                              publish_time_ns=t + 2_000_000, seq=1, latched=True)))
    return sent


def on_the_wire(sent: list[tuple[str, str, Any, bytes]]) -> list[bytes]:
    """The frames as the robot's client puts them on the wire: big ones fragmented, the
    map compressed."""
    frames: list[bytes] = []
    for i, (topic, _type, _msg, frame) in enumerate(sent):
        if topic == "/husky1/map":
            frame = compress(frame, codec=CompressionCodec.ZSTD, topic=topic, no_drop=False)
        frames += fragments.split(frame, topic=topic, message_id=i + 1,
                                  max_fragment_bytes=16_384, no_drop=False)
    return frames


async def test_recorded_file_reads_back_equal_with_rosbags_and_mcap(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:
    sent = mixed_messages()
    async with make_server(recording=recording(tmp_path)) as srv:
        assert srv.recorder is not None
        async with client(srv, source=ROBOT) as robot, client(srv, token=ALICE_TOKEN) as alice:
            for frame in on_the_wire(sent):
                await robot.send(frame)
            # Not recorded: alice is not husky1 (identities), husky1 only sends /husky1/.*
            await alice.send(published(1)[0][3])
            await alice.send(published(1, topic="/other/chat")[0][3])
            recorder = srv.recorder
            await wait_for(lambda: recorder.snapshot()["messages"] == len(sent), DEADLINE_S)
    [rec] = files.scan(tmp_path / "rec")
    assert files.is_complete(rec.path)
    expected = expected_rows(sent)
    assert read_with_rosbags(rec.path) == expected
    assert read_with_mcap(rec.path) == expected
    with AnyReader([rec.path]) as reader:  # rosbag2's channel metadata: QoS per topic
        durability = {c.topic: c.ext.offered_qos_profiles[0].durability.name
                      for c in reader.connections}
    assert durability["/husky1/map"] == "TRANSIENT_LOCAL"  # latched
    assert durability["/husky1/chat"] == "VOLATILE"
    summary = files.describe(rec.path)
    assert summary["complete"] and summary["messages"] == len(sent)
    assert summary["topics"] == ["/husky1/chat", "/husky1/cloud", "/husky1/map", "/husky1/pose"]


async def test_open_file_is_readable_while_written(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:
    sent = published(50)
    config = recording(tmp_path, flush_interval_s=0.05)
    async with make_server(recording=config) as srv, client(srv, source=ROBOT) as robot:
        for _, _, _, frame in sent[:30]:
            await robot.send(frame)
        [rec] = await _one_file(tmp_path)
        # The writer flushes complete chunks: the open file (no footer yet) shows them.
        await wait_for(lambda: len(list(files.read_messages(rec.path))) == 30, DEADLINE_S)
        assert not files.is_complete(rec.path)
        rows = [(c.topic, s.name if s else "", m.log_time, m.data)
                for s, c, m in files.read_messages(rec.path)]
        assert rows == expected_rows(sent[:30])
        # rosbags wants the closing magic: an exported copy of the open file has it.
        assert files.export(rec.path, tmp_path / "copy.mcap") == 30
        assert read_with_rosbags(tmp_path / "copy.mcap") == expected_rows(sent[:30])
        for _, _, _, frame in sent[30:]:
            await robot.send(frame)
        await wait_for(lambda: len(list(files.read_messages(rec.path))) == 50, DEADLINE_S)
    assert files.is_complete(rec.path)
    assert read_with_mcap(rec.path) == expected_rows(sent)


async def _one_file(tmp_path: Path) -> list[files.RecordingFile]:
    await wait_for(lambda: len(files.scan(tmp_path / "rec")) == 1, DEADLINE_S)
    return files.scan(tmp_path / "rec")


async def test_recording_survives_a_restart(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:
    first, second = published(10), published(10, start_ns=1_800_000_000_000_000_000)
    for batch in (first, second):
        async with make_server(recording=recording(tmp_path)) as srv, \
                client(srv, source=ROBOT) as robot:
            for _, _, _, frame in batch:
                await robot.send(frame)
            await wait_for(lambda srv=srv: srv.recorder.snapshot()["messages"] == 10, DEADLINE_S)
    old, new = files.scan(tmp_path / "rec")  # oldest first
    assert old.name < new.name or old.modified_s <= new.modified_s
    for rec, batch in ((old, first), (new, second)):
        assert files.is_complete(rec.path)
        assert read_with_mcap(rec.path) == expected_rows(batch)
        assert read_with_rosbags(rec.path) == expected_rows(batch)


async def test_disk_bound_holds_under_a_flood(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:
    max_total = 256 * 1024
    config = recording(tmp_path, max_file_bytes=48 * 1024, max_total_bytes=max_total,
                       chunk_bytes=8 * 1024, flush_interval_s=0.05)
    codec = default_codec()
    cls = codec.registry.get(STRING).cls
    rng = random.Random(0)
    texts = [rng.randbytes(500).hex() for _ in range(2000)]  # ~500 B each after zstd
    peak = 0
    async with make_server(recording=config) as srv, client(srv, source=ROBOT) as robot:
        assert srv.recorder is not None
        for i in range(2000):  # ~1 MB compressed: four times the bound
            await robot.send(codec.encode(cls(texts[i]), STRING, "/husky1/flood",
                                          publish_time_ns=time.time_ns(), seq=i + 1))
            if i % 50 == 0:
                peak = max(peak, sum(f.size_bytes for f in files.scan(config.directory)))
        recorder = srv.recorder
        await wait_for(lambda: recorder.snapshot()["messages"]
                       + sum(recorder.snapshot()["dropped"].values()) == 2000, DEADLINE_S)
        status, body = await http_get(srv.port, "/metrics")
        peak = max(peak, sum(f.size_bytes for f in files.scan(config.directory)))
    assert status == 200
    on_disk = files.scan(config.directory)
    assert sum(f.size_bytes for f in on_disk) <= max_total
    assert peak <= max_total
    assert recorder.snapshot()["deleted_files"]["max_total_bytes"] >= 3
    assert 'fleetctl_recording_deleted_files_total{reason="max_total_bytes"}' in body
    # What is left is the newest data, readable, in order.
    rows = [r for f in on_disk for r in read_with_mcap(f.path)]
    assert [r[2] for r in rows] == sorted(r[2] for r in rows)
    assert rows[-1][3] == cdr(STRING, cls(texts[-1]))


async def test_queue_overflow_drops_are_counted_and_logged(
        make_server: Callable[..., RelayServer], tmp_path: Path,
        caplog: pytest.LogCaptureFixture) -> None:
    sent = published(5)
    config = recording(tmp_path, queue_bytes=len(sent[0][3]) - 1)  # no frame fits
    caplog.set_level(logging.WARNING, "fleetctl.server.recording")
    async with make_server(recording=config) as srv, client(srv, source=ROBOT) as robot:
        assert srv.recorder is not None
        for _, _, _, frame in sent:
            await robot.send(frame)
        recorder = srv.recorder
        await wait_for(lambda: recorder.snapshot()["dropped"]["queue_full"] == 5, DEADLINE_S)
        _status, body = await http_get(srv.port, "/metrics")
    assert 'fleetctl_recording_dropped_total{reason="queue_full"} 5' in body
    warnings = [r for r in caplog.records if "queue_full" in r.getMessage()]
    assert len(warnings) == 1  # rate-limited: one line for the burst


def test_age_bound_deletes_old_closed_files(tmp_path: Path) -> None:
    old, current = tmp_path / "fleet_a.mcap", tmp_path / "fleet_b.mcap"
    old.write_bytes(b"x" * 10)
    current.write_bytes(b"y" * 10)
    now = time.time() + 1000
    deleted = files.enforce_bounds(tmp_path, current, 10**9, max_age_s=100, now_s=now)
    assert [(f.name, reason) for f, reason in deleted] == [("fleet_a.mcap", "max_age")]
    assert not old.exists() and current.exists()  # the file being written is never deleted


async def test_a_dead_worker_is_logged_counted_and_restarted(
        make_server: Callable[..., RelayServer], tmp_path: Path,
        caplog: pytest.LogCaptureFixture) -> None:
    sent = published(6)
    caplog.set_level(logging.WARNING, "fleetctl.server.recording")
    async with make_server(recording=recording(tmp_path)) as srv, \
            client(srv, source=ROBOT) as robot:
        recorder = srv.recorder
        assert recorder is not None and recorder.worker_pid is not None
        first_pid = recorder.worker_pid
        await robot.send(sent[0][3])
        await wait_for(lambda: recorder.snapshot()["messages"] == 1, DEADLINE_S)
        os.kill(first_pid, signal.SIGKILL)
        await wait_for(lambda: any("recording worker exited" in r.getMessage()
                                   for r in caplog.records), DEADLINE_S)
        for _, _, _, frame in sent[1:3]:  # before the restart (1 s later): dropped
            await robot.send(frame)
        await wait_for(lambda: srv.metrics.messages_in["/husky1/chat"] == 3, DEADLINE_S)
        await wait_for(lambda: recorder.worker_pid not in (None, first_pid), DEADLINE_S)
        for _, _, _, frame in sent[3:]:
            await robot.send(frame)
        # Every frame recorded or counted as dropped; the counters go on from the dead
        # worker's (Prometheus counters never go back).
        await wait_for(lambda: recorder.snapshot()["messages"]
                       + recorder.snapshot()["dropped"]["worker_exited"] == 6, DEADLINE_S)
        snap = recorder.snapshot()
        assert snap["messages"] >= 4 and snap["files_opened"] == 2
    old, new = files.scan(tmp_path / "rec")
    assert [m.data for _, _, m in files.read_messages(old.path)] in (
        [], [cdr(STRING, sent[0][2])])  # what the killed worker flushed, if anything
    assert files.is_complete(new.path)
    assert read_with_mcap(new.path)[-3:] == expected_rows(sent[3:])


async def test_a_restarted_worker_starts_its_file_with_the_latched_map(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:
    # A robot sends its map once (latched): a worker restart must not leave the new file,
    # and so every file after it, without one until the robot resends it.
    sent = mixed_messages()
    topic, _, _, frame = sent[-1]  # compressed and fragmented, as a robot sends a map
    map_frames = fragments.split(
        compress(frame, codec=CompressionCodec.ZSTD, topic=topic, no_drop=False),
        topic=topic, message_id=7, max_fragment_bytes=256, no_drop=False)
    assert len(map_frames) > 1
    async with make_server(recording=recording(tmp_path)) as srv, \
            client(srv, source=ROBOT) as robot:
        recorder = srv.recorder
        assert recorder is not None and recorder.worker_pid is not None
        for frame in map_frames:
            await robot.send(frame)
        await wait_for(lambda: recorder.snapshot()["messages"] == 1, DEADLINE_S)
        first_pid = recorder.worker_pid
        os.kill(first_pid, signal.SIGKILL)
        await wait_for(lambda: recorder.worker_pid not in (None, first_pid), DEADLINE_S)
        await robot.send(sent[0][3])  # a chat line after the restart
        await wait_for(lambda: recorder.snapshot()["messages"] >= 3, DEADLINE_S)
    new = files.scan(tmp_path / "rec")[-1]
    assert files.is_complete(new.path)
    # Both, each with its own publish time as its log time (the map's is the later).
    assert sorted(read_with_mcap(new.path)) == sorted(expected_rows([sent[-1], sent[0]]))


async def test_frames_the_relay_refuses_are_never_recorded(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:
    config = recording(tmp_path, rules=(RecordingRule(".*"),))
    async with make_server(recording=config) as srv, client(srv, source=ROBOT) as robot:
        recorder = srv.recorder
        assert recorder is not None
        await robot.send(published(1, topic="/husky2/chat")[0][3])  # not husky1's to send
        await robot.send(published(1)[0][3])
        await wait_for(lambda: recorder.snapshot()["messages"] == 1, DEADLINE_S)
        assert srv.metrics.errors["unauthorized_send"] == 1
    [rec] = files.scan(tmp_path / "rec")
    assert [row[0] for row in read_with_mcap(rec.path)] == ["/husky1/chat"]


class _TimerSpy:
    """Stands in for the event loop in :meth:`Recorder.offer`: records the flushes armed."""

    def __init__(self) -> None:
        self.armed: list[float] = []  # delay of each flush armed
        self.cancelled = 0

    def time(self) -> float:
        return 100.0

    def call_at(self, when: float, _callback: Callable[[], None]) -> Any:
        self.armed.append(when - 100.0)
        spy = self

        class Handle:
            def cancel(self) -> None:
                spy.cancelled += 1

        return Handle()


def test_one_socket_read_of_many_frames_arms_the_flush_at_most_twice(tmp_path: Path) -> None:
    # A socket read can hand the relay thousands of frames before the loop runs a timer.
    # Re-arming the flush for each frame past FLUSH_BYTES cost a quarter of the relay's
    # time at full load (benchmarks/recording_throughput.py: 0.70x, now 0.87x).
    recorder = Recorder(recording(tmp_path, rules=(RecordingRule(".*"),)))
    spy = _TimerSpy()
    recorder._loop = spy  # type: ignore[assignment]
    perms = PermissionsPool().get([])
    frame = bytes(1000)
    for _ in range(3 * FLUSH_BYTES // len(frame)):
        recorder.offer(1, perms, "/husky1/chat", frame)
    assert spy.armed == [pytest.approx(FLUSH_DELAY_S), 0.0]  # delayed, then "now" once full
    assert spy.cancelled == 1
    assert recorder.queued_bytes == 3 * FLUSH_BYTES // len(frame) * (HEADER.size + len(frame))


OWN_TYPES = (("my_robot_msgs/msg/Status", "uint8 mode\nmy_robot_msgs/Battery battery\n"),
             ("my_robot_msgs/msg/Battery", "float32 voltage_v\n"))


async def test_the_fleets_own_message_types_are_recorded(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:
    """The worker decoded with the default registry: a topic of a type from server.yaml's
    msg_types was dropped as malformed, every message of it."""
    codec = codec_for(OWN_TYPES)
    types = codec.registry.typestore.types
    status = "my_robot_msgs/msg/Status"
    async with make_server(recording=recording(tmp_path), msg_types=OWN_TYPES) as srv:
        assert srv.recorder is not None
        async with client(srv, source=ROBOT) as robot:
            for mode in (1, 2, 3):
                msg = types[status](mode=mode, battery=types["my_robot_msgs/msg/Battery"](
                    voltage_v=24.5))
                await robot.send(codec.encode(msg, status, "/husky1/robot_status", seq=mode))
            recorder = srv.recorder
            await wait_for(lambda: recorder.snapshot()["messages"] == 3, DEADLINE_S)
        assert recorder.snapshot()["dropped"]["malformed"] == 0
        types_file = recorder._types_file  # the definitions handed to the worker
        assert types_file is not None and stat.S_IMODE(types_file.stat().st_mode) == 0o600
    assert not types_file.exists()  # removed when the server stopped
    [rec] = files.scan(tmp_path / "rec")
    with AnyReader([rec.path]) as reader:  # the types from the file's own schemas
        got = [(c.msgtype, reader.deserialize(raw, c.msgtype)) for c, _t, raw in
               reader.messages()]
    assert [(t, m.mode, m.battery.voltage_v) for t, m in got] == [
        (status, mode, 24.5) for mode in (1, 2, 3)]
