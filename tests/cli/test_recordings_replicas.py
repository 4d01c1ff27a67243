"""``fleetctl recordings --server A --server B``: a fleet of replicas records sharded by
the replica that accepted each frame; the command lists and fetches across them."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from pathlib import Path

import pytest

from fleetctl.cli.main import main
from fleetctl.server.app import RelayServer
from fleetctl.server.cluster.config import ClusterConfig
from fleetctl.server.config import ServerConfig
from fleetctl.server.recording import files
from fleetctl.server.recording.config import RecordingConfig, RecordingRule
from tests.server.cluster.natsproc import free_port
from tests.server.conftest import (  # noqa: F401
    auth_map,
    client,
    make_server,
    wait_for,
)
from tests.support import string_frame

DEADLINE_S = 30.0


def recording(directory: Path, label: str) -> RecordingConfig:
    return RecordingConfig(directory, (RecordingRule(".*"),), flush_interval_s=0.05,
                           file_label=label)


def test_file_names_carry_the_label() -> None:
    path = files.new_path(Path("/tmp/none"), 0.0, "relay-2")
    assert path.name == "fleet_relay-2_19700101T000000Z.mcap"
    assert files.new_path(Path("/tmp/none"), 0.0).name == "fleet_19700101T000000Z.mcap"


def test_a_replica_labels_its_files_with_its_cluster_name(tmp_path: Path) -> None:
    config = ServerConfig(listen_host="127.0.0.1", listen_port=0, auth_map=tmp_path / "a.yaml",
                          database=tmp_path / "a.db",
                          recording=RecordingConfig(tmp_path / "rec", (RecordingRule(".*"),)),
                          cluster=ClusterConfig(name="relay-7", nats_urls=("nats://h:1",)))
    server = RelayServer(config, auth_map())  # not started: no NATS needed
    assert server.recorder is not None and server.recorder.config.file_label == "relay-7"


async def test_list_and_fetch_across_replicas(
        make_server: Callable[..., RelayServer], tmp_path: Path,  # noqa: F811
        capsys: pytest.CaptureFixture[str]) -> None:
    async with make_server(recording=recording(tmp_path / "a", "relay-a")) as a, \
            make_server(recording=recording(tmp_path / "b", "relay-b"),
                        database=tmp_path / "b.db") as b, \
            client(a, source="127.0.0.2") as husky1, client(b, source="127.0.0.3") as husky2:
        await husky1.send(string_frame("/husky1/chat", "on a", seq=1))
        await husky2.send(string_frame("/husky2/chat", "on b", seq=1))
        for srv in (a, b):  # each file on disk holds its message (flushed)
            recorder = srv.recorder
            assert recorder is not None
            await wait_for(lambda r=recorder: r.snapshot()["messages"] == 1, DEADLINE_S)
            directory = recorder.config.directory
            await wait_for(lambda d=directory: [len(list(files.read_messages(f.path)))
                                                for f in files.scan(d)] == [1], DEADLINE_S)
        dead = f"http://127.0.0.1:{free_port()}/"
        argv = ["recordings", "list", "--server", a.url, "-s", b.url, "-s", dead, "-o", "json"]
        assert await asyncio.to_thread(main, argv) == 0
        out = capsys.readouterr()
        listed = json.loads(out.out)
        assert sorted((r["name"].split("_")[1], r["server"]) for r in listed) == [
            ("relay-a", a.url), ("relay-b", b.url)]
        assert dead in out.err  # named, while the others are listed
        argv = ["recordings", "list", "--server", a.url, "-s", b.url]  # text: TOPICS last
        assert await asyncio.to_thread(main, argv) == 0
        head, *rows = capsys.readouterr().out.splitlines()
        assert head.split()[-2:] == ["SERVER", "TOPICS"]
        assert sorted(row.split()[-1] for row in rows) == ["/husky1/chat", "/husky2/chat"]
        on_b = next(r["name"] for r in listed if r["server"] == b.url)
        argv = ["recordings", "fetch", on_b, "--to", str(tmp_path), "-s", a.url, "-s", b.url]
        assert await asyncio.to_thread(main, argv) == 0
        assert [c.topic for _, c, _ in files.read_messages(tmp_path / on_b)] == ["/husky2/chat"]
        argv = ["recordings", "fetch", "fleet_nowhere.mcap", "--to", str(tmp_path),
                "-s", a.url, "-s", b.url]
        assert await asyncio.to_thread(main, argv) != 0
        assert "is on none of" in capsys.readouterr().err
    assert main(["recordings", "list", "-s", dead]) != 0  # nobody answers: an error
