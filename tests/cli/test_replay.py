"""``fleetctl replay``: a damaged recording (one line, the readable part still played); a
fleet's TLS port (``--ca-file``); a server it never reaches (at once, saying why)."""

from __future__ import annotations

import asyncio
import json
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from fleetctl.cli.main import main
from fleetctl.cli.replay import ReplayOptions, replay
from fleetctl.errors import ExitCode, FleetError
from fleetctl.server.app import RelayServer
from fleetctl.server.config import WebConfig
from tests.cli.test_recordings import STRING, T0, write_recording
from tests.server.conftest import (  # noqa: F401
    ALICE_TOKEN,
    BOB_TOKEN,
    client,
    make_server,
    subscribe,
)
from tests.server.foxglove.conftest import web_config  # noqa: F401
from tests.server.recording.damaged import damage, damaged_recording
from tests.support import decode_text


async def test_a_damaged_chunk_is_one_line_after_the_readable_messages(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    # A chunk that did not decompress ended the replay with a zstandard traceback.
    first = damaged_recording(tmp_path / "rec.mcap")
    assert first > 0
    async with make_server() as srv:
        options = ReplayOptions(srv.url, rate=None, token=ALICE_TOKEN)
        with pytest.raises(FleetError) as info:
            await replay(tmp_path / "rec.mcap", options)
        received = srv.metrics.messages_in.get("/husky1_replay/chat", 0)
    assert str(info.value).startswith(
        f"{tmp_path / 'rec.mcap'}: damaged data, the rest of the file cannot be read (")
    assert str(info.value).endswith(f"); the {first} message(s) before it were replayed")
    assert received == first


def test_a_damaged_recording_on_the_command_line_is_no_traceback(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # The first chunk damaged: nothing to send, so no server is needed (port 9: none).
    path = tmp_path / "rec.mcap"
    damaged_recording(path)
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    damage(path, min(summary.chunk_indexes, key=lambda c: c.chunk_start_offset))
    code = main(["replay", str(path), "--server", "ws://127.0.0.1:9/", "--rate", "0"])
    err = capsys.readouterr().err
    assert code == 1, err
    assert "Traceback" not in err
    assert f"{path}: damaged data, the rest of the file cannot be read (" in err
    assert err.rstrip().endswith("nothing before it to replay")


def alice_token_file(tmp_path: Path) -> Path:
    token = tmp_path / "token"
    token.write_text(ALICE_TOKEN + "\n")
    token.chmod(0o600)  # else a warning comes first on stderr
    return token


async def test_replays_into_a_fleets_tls_port_with_its_ca_file(
        make_server: Callable[..., RelayServer], web_config: WebConfig,  # noqa: F811
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`fleetctl up` publishes one port, TLS with the fleet's self-signed certificate:
    replay had no --ca-file, so it could not reach a deployed fleet at all."""
    write_recording(tmp_path / "rec.mcap", 5, step_ns=1_000_000)
    async with make_server(web=web_config) as srv:
        code = await asyncio.to_thread(main, [
            "replay", str(tmp_path / "rec.mcap"), "--server",
            f"wss://127.0.0.1:{srv.web_port}/", "--token-file", str(alice_token_file(tmp_path)),
            "--ca-file", str(web_config.tls_cert), "--rate", "0", "-o", "json"])
        received = srv.metrics.messages_in.get("/husky1_replay/chat", 0)
    assert code == 0, capsys.readouterr().err
    assert json.loads(capsys.readouterr().out)["messages"] == 5 and received == 5


async def test_a_server_never_reached_fails_at_once_saying_why(
        make_server: Callable[..., RelayServer], web_config: WebConfig,  # noqa: F811
        tmp_path: Path) -> None:
    """A replay that never connected waited 30 s behind the link's 'retrying' warning,
    then said '5 message(s) still queued ... never connected' (exit 6), whatever the
    cause: an untrusted certificate, ws:// to the TLS port, nothing listening."""
    write_recording(tmp_path / "rec.mcap", 5, step_ns=1_000_000)
    token = str(alice_token_file(tmp_path))
    async with make_server(web=web_config) as srv:
        closed = await asyncio.to_thread(_free_port)
        for url, expected in (
                (f"wss://127.0.0.1:{srv.web_port}/",
                 "its certificate is not trusted (self-signed certificate): give the CA that "
                 "signed it with --ca-file"),
                (f"ws://127.0.0.1:{srv.web_port}/",
                 "the server closed the connection without an answer (a TLS port? use "
                 "https:// or wss://)"),
                (f"wss://127.0.0.1:{srv.port}/",
                 "the connection was accepted but the handshake got no answer in time (a plain "
                 "ws:// port? use the TLS port"),
                (f"ws://127.0.0.1:{closed}/", "cannot reach it: "),
        ):
            started = time.monotonic()
            code, err = await _replay_process(tmp_path / "rec.mcap", "--server", url,
                                              "--token-file", token, "--rate", "0")
            assert code == ExitCode.FAILURE, err
            assert err.startswith(f"fleetctl: error: replay: --server {url}: {expected}"), err
            assert err.count("\n") == 1  # not the link's "retrying every 5 s" beside it
            assert time.monotonic() - started < 15  # not the 30 s drain deadline


async def _replay_process(*args: object) -> tuple[int, str]:
    """``fleetctl replay ARGS`` in a process of its own (its link logs to stderr there,
    through Python's last resort handler; pytest's log capture hides that here):
    the exit code and stderr."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "fleetctl.cli.main", "replay", *map(str, args),
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
    _out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    return proc.returncode, err.decode()


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def test_ca_file_is_for_wss_only(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_recording(tmp_path / "rec.mcap", 1)
    assert main(["replay", str(tmp_path / "rec.mcap"), "--server", "ws://127.0.0.1:9/",
                 "--ca-file", str(tmp_path / "ca.pem")]) == ExitCode.CONFIG
    assert capsys.readouterr().err == (
        "fleetctl: error: --ca-file: verifies a wss:// server; ws://127.0.0.1:9/ is plain "
        "ws:// (no TLS)\n")


async def test_topics_refused_are_one_line(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    """A token without send rules for a fleet recording's 19 topics printed the link's
    19 'server error unauthorized_send on ...' warnings above the error that names them."""
    write_recording(tmp_path / "rec.mcap", 5, step_ns=1_000_000)
    token = tmp_path / "bob.token"
    token.write_text(BOB_TOKEN + "\n")
    token.chmod(0o600)
    async with make_server() as srv:
        code, err = await _replay_process(tmp_path / "rec.mcap", "-s", srv.url,
                                          "--token-file", token, "--rate", "0")
    assert code == ExitCode.FAILURE
    notice, error = err.splitlines()
    assert notice.startswith("fleetctl: warning: replay: topics renamed so that no live robot")
    assert error == ("fleetctl: error: replay: the server refused 1 topic(s), no send "
                     "permission for this identity: /husky1_replay/chat (give it send "
                     "rules, or --remap to topics it may send)")


async def test_replays_a_rosbag2_bag_directory(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    """`ros2 bag record -s mcap` makes a directory (metadata.yaml and NAME_0.mcap, ...):
    replay said 'is a directory, not a recording file'. Its files are played in the
    order metadata.yaml lists them, as one recording."""
    store = get_typestore(Stores.ROS2_JAZZY)
    string = store.types[STRING]
    bag = tmp_path / "bag"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        chat = writer.add_connection("/husky1/chat", STRING, typestore=store)
        for i in range(4):
            writer.write(chat, T0 + i * 1_000_000,
                         store.serialize_cdr(string(data=f"message {i}"), STRING))
    (bag / "notes.txt").write_text("not a recording")
    async with make_server() as srv, client(srv, token=ALICE_TOKEN) as viewer:
        assert (await subscribe(viewer, "/husky1_replay/.*"))["type"] == "subscribed"
        result = await replay(bag, ReplayOptions(srv.url, rate=None, token=ALICE_TOKEN))
        got = [decode_text(f) for f in await _frames(viewer, 4)]
    assert result.messages == 4 and got == [f"message {i}" for i in range(4)]


async def _frames(viewer: Any, n: int) -> list[bytes]:
    frames: list[bytes] = []
    while len(frames) < n:
        frame = await asyncio.wait_for(viewer.recv(), 5.0)
        if isinstance(frame, bytes):
            frames.append(frame)
    return frames


def test_a_directory_without_recordings_says_what_it_takes(tmp_path: Path) -> None:
    (tmp_path / "bag").mkdir()
    (tmp_path / "bag" / "rec_0.db3").write_bytes(b"SQLite format 3\0")
    with pytest.raises(FleetError) as caught:
        asyncio.run(replay(tmp_path / "bag", ReplayOptions("ws://127.0.0.1:9/")))
    assert str(caught.value) == (
        f"{tmp_path / 'bag'}: no .mcap file in this directory (replay takes an MCAP file, or "
        "a rosbag2 bag recorded with `-s mcap`; a .db3 bag converts with rosbags-convert)")
