"""``fleetctl recordings merge --server A --server B --robot X``: a robot that moved from
replica A to replica B of a real NATS cluster has its run in files of both; the merged
file holds all of it, once, in order, as rosbags reads it; a window of it starts with the
latched map from before the window."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import pytest
from rosbags.highlevel import AnyReader

from fleetctl.cli.main import main
from fleetctl.errors import ExitCode
from fleetctl.server.app import RelayServer
from fleetctl.server.recording import files
from fleetctl.server.recording.config import RecordingConfig, RecordingRule
from fleetctl.wire.codec import default_codec
from fleetctl.wire.metadata import read_root
from tests.server.cluster.conftest import nats_cluster, replica_config  # noqa: F401
from tests.server.cluster.natsproc import NatsServer, free_port
from tests.server.conftest import (
    ALICE_TOKEN,
    auth_map,
    client,
    next_binary,
    subscribe,
    wait_for,
)
from tests.support import decode_text, string_frame

DEADLINE_S = 20.0
STRING = "std_msgs/msg/String"


def recording_replica(tmp_path: Path, name: str, nats: NatsServer) -> RelayServer:
    config = dataclasses.replace(
        replica_config(tmp_path, name, [nats.url]),
        recording=RecordingConfig(tmp_path / name, (RecordingRule("/husky[12]/(chat|map)"),),
                                  flush_interval_s=0.05))  # not the probes
    return RelayServer(config, auth_map())


async def until_crossing(sender: Any, receiver: Any) -> None:
    """Send probes (not recorded) until one reaches *receiver*: the subscription has
    reached the sender's NATS server (interest crosses cluster routes asynchronously)."""
    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        await sender.send(string_frame("/husky1/probe", "probe"))
        try:
            await next_binary(receiver, 0.05)
            return
        except TimeoutError:
            continue
    raise AssertionError("no probe crossed the replicas")


async def chat_texts(ws: Any, n: int) -> list[str]:
    """The texts of the next *n* frames that are not probes (a slow reader may get only
    the newest of a topic: the relay supersedes droppable frames in its queue)."""
    texts: list[str] = []
    while len(texts) < n:
        frame = await next_binary(ws, DEADLINE_S)
        if read_root(frame)[0].topic != "/husky1/probe":
            texts.append(decode_text(frame))
    return texts


def latched_map() -> bytes:
    codec = default_codec()
    return codec.encode(codec.registry.get(STRING).cls("the map"), STRING, "/husky1/map",
                        latched=True, seq=1, publish_time_ns=time.time_ns())


async def on_disk(server: RelayServer, messages: int) -> None:
    """Wait until *server*'s recorder has flushed *messages* messages to its files."""
    recorder = server.recorder
    assert recorder is not None
    directory = recorder.config.directory
    await wait_for(lambda: sum(len(list(files.read_messages(f.path)))
                               for f in files.scan(directory)) == messages, DEADLINE_S)


def read_back(path: Path) -> list[tuple[str, int, str]]:
    with AnyReader([path]) as reader:
        return [(c.topic, t, reader.deserialize(raw, c.msgtype).data)
                for c, t, raw in reader.messages()]


async def test_a_robot_that_moved_from_a_to_b_is_merged_into_one_file(
        tmp_path: Path, nats_cluster: list[NatsServer],  # noqa: F811
        capsys: pytest.CaptureFixture[str]) -> None:
    a = recording_replica(tmp_path, "relay-a", nats_cluster[0])
    b = recording_replica(tmp_path, "relay-b", nats_cluster[1])
    the_map = latched_map()  # published first (the frames carry their publish time)
    sent = [string_frame("/husky1/chat", f"message {i:02d}", seq=i + 1) for i in range(20)]
    async with a, b, client(b, token=ALICE_TOKEN) as viewer:
        assert (await subscribe(viewer, "/husky1/.*"))["type"] == "subscribed"
        async with client(a, source="127.0.0.2") as robot:  # husky1 on A
            await until_crossing(robot, viewer)
            await robot.send(the_map)
            for frame in sent[:10]:
                await robot.send(frame)
            # B relays them to its viewer (the newest of a droppable topic at least),
            # and records none of them.
            while "message 09" not in await chat_texts(viewer, 1):
                pass
        async with client(b, source="127.0.0.2") as robot, \
                client(b, source="127.0.0.3") as husky2:  # husky1 moved to B
            await robot.send(sent[9])  # sent again after the move: recorded on A and B
            for frame in sent[10:]:
                await robot.send(frame)
            await husky2.send(string_frame("/husky2/chat", "not husky1's"))
            await on_disk(a, 11)
            await on_disk(b, 12)
        out = tmp_path / "husky1.mcap"
        argv = ["recordings", "merge", "--server", a.url, "--server", b.url,
                "--robot", "husky1", "--to", str(out), "-o", "json"]
        assert await asyncio.to_thread(main, argv) == 0
        result = json.loads(capsys.readouterr().out)
        assert (result["files"], result["messages"], result["duplicates"]) == (2, 21, 1)
        assert result["topics"] == ["/husky1/chat", "/husky1/map"]
        assert len(result["still_open"]) == 2  # both files are being written
        merged = read_back(out)
        assert [text for _, _, text in merged] == [
            "the map", *(f"message {i:02d}" for i in range(20))]
        times = [t for _, t, _ in merged]
        assert times == sorted(times)
        assert (times[0], times[-1]) == (result["start_ns"], result["end_ns"])
        # A window from message 10 on starts with the map A recorded long before it.
        since = times[11]
        argv = ["recordings", "merge", "--server", a.url, "--server", b.url,
                "--robot", "husky1", "--since", f"{since // 10**9}.{since % 10**9:09d}",
                "--to", str(tmp_path / "window.mcap"), "-o", "json"]
        assert await asyncio.to_thread(main, argv) == 0
        result = json.loads(capsys.readouterr().out)
        assert (result["messages"], result["carried"]) == (11, 1)
        assert read_back(tmp_path / "window.mcap") == [
            ("/husky1/map", since, "the map"),
            *(("/husky1/chat", t, text) for _, t, text in merged[11:])]
        # A replica that does not answer is an error naming it: the merge would miss its
        # part of the run.
        dead = f"http://127.0.0.1:{free_port()}/"
        argv = ["recordings", "merge", "-s", a.url, "-s", dead, "--robot", "husky1",
                "--to", str(tmp_path / "partial.mcap")]
        assert await asyncio.to_thread(main, argv) == ExitCode.FAILURE
        err = capsys.readouterr().err
        assert f"--server {dead}" in err and "Traceback" not in err
        assert not (tmp_path / "partial.mcap").exists()
        argv = ["recordings", "merge", "-s", a.url, "-s", b.url, "--robot", "husky9",
                "--to", str(tmp_path / "none.mcap")]
        assert await asyncio.to_thread(main, argv) == ExitCode.FAILURE
        assert "no recording of robot 'husky9'" in capsys.readouterr().err
