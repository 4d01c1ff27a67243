"""``fleetctl recordings`` (list, fetch) and ``fleetctl replay`` against a real relay."""

from __future__ import annotations

import asyncio
import json
import os
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from fleetctl.cli.main import main
from fleetctl.cli.recordings import Remote, fetch_remote
from fleetctl.cli.replay import ReplayOptions, replay
from fleetctl.errors import ExitCode, FleetError
from fleetctl.server.app import RelayServer
from fleetctl.server.config import ServerConfig
from fleetctl.server.recording import files
from fleetctl.server.recording.config import RecordingConfig, RecordingRule
from fleetctl.server.recording.latched import is_latched
from fleetctl.server.recording.mcapfile import McapFile
from fleetctl.wire.codec import default_codec
from tests.server.conftest import (  # noqa: F401
    ALICE_TOKEN,
    BOB_TOKEN,
    auth_map,
    client,
    make_server,
    subscribe,
)
from tests.support import decode_text

STRING = "std_msgs/msg/String"
T0 = 1_700_000_000_000_000_000


def write_recording(path: Path, n: int, *, step_ns: int = 20_000_000, close: bool = True,
                    topic: str = "/husky1/chat") -> McapFile:
    """A recording of *n* String messages, *step_ns* apart, as the server writes it."""
    registry = default_codec().registry
    cls = registry.get(STRING).cls
    out = McapFile(path, registry, 1024)
    for i in range(n):
        msg = cls(f"message {i}")
        out.write(topic, STRING, bytes(registry.typestore.serialize_cdr(msg, STRING)),
                  T0 + i * step_ns, i + 1)
    if close:
        out.close()
    else:
        out.flush()
    return out


def test_list_shows_complete_and_open_files(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    write_recording(tmp_path / "fleet_a.mcap", 5)
    still_open = write_recording(tmp_path / "fleet_b.mcap", 3, close=False)
    assert main(["recordings", "list", "--dir", str(tmp_path), "-o", "json"]) == 0
    found = json.loads(capsys.readouterr().out)
    assert [(r["name"], r["complete"], r["messages"], r["topics"]) for r in found] == [
        ("fleet_a.mcap", True, 5, ["/husky1/chat"]),
        ("fleet_b.mcap", False, 3, ["/husky1/chat"])]
    assert found[0]["start_ns"] == T0 and found[0]["end_ns"] == T0 + 4 * 20_000_000
    assert main(["recordings", "list", "--dir", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "fleet_b.mcap" in text and "writing" in text
    still_open.close()


def test_list_cuts_many_topics_to_the_terminal_width(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    topics = [f"/husky1/sensor_{i:02d}/data" for i in range(20)]
    registry = default_codec().registry
    out = McapFile(tmp_path / "fleet_a.mcap", registry, 1024)
    cdr = bytes(registry.typestore.serialize_cdr(registry.get(STRING).cls("x"), STRING))
    for i, topic in enumerate(topics):
        out.write(topic, STRING, cdr, T0 + i, i + 1)
    out.close()
    monkeypatch.setenv("COLUMNS", "160")
    assert main(["recordings", "list", "--dir", str(tmp_path)]) == 0
    head, row = capsys.readouterr().out.splitlines()
    assert head.endswith("TOPICS") and len(row) <= 160
    assert row.endswith(" more") and topics[0] in row and topics[-1] not in row
    assert main(["recordings", "list", "--dir", str(tmp_path), "--all-topics"]) == 0
    assert capsys.readouterr().out.splitlines()[1].endswith(", ".join(topics))
    assert main(["recordings", "list", "--dir", str(tmp_path), "-o", "json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["topics"] == topics


def test_list_reads_the_directory_from_server_yaml(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "rec").mkdir()
    write_recording(tmp_path / "rec" / "fleet_a.mcap", 2)
    config = tmp_path / "server.yaml"
    config.write_text("auth_map: auth.yaml\nrecording:\n  directory: rec\n"
                      "  rules: [{topic: '.*'}]\n")
    assert main(["recordings", "list", "-c", str(config), "-o", "json"]) == 0
    assert [r["name"] for r in json.loads(capsys.readouterr().out)] == ["fleet_a.mcap"]
    config.write_text("auth_map: auth.yaml\n")
    assert main(["recordings", "list", "-c", str(config)]) == ExitCode.CONFIG
    assert "field 'recording' is not set" in capsys.readouterr().err
    assert main(["recordings", "list"]) == ExitCode.CONFIG


def test_list_with_a_deployed_fleets_server_yaml_says_where_the_recordings_are(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """On the server host, `--config FLEET/server/server.yaml` said `no recordings in
    FLEET/server/recordings`: under `fleetctl up` they are in the data volume."""
    from fleetctl.deploy import operations as ops

    fleet = tmp_path / "yard"
    ops.create_fleet(fleet, https_port=9443)
    with (fleet / "fleet.yaml").open("a") as f:
        f.write("recording:\n  topics: ['/.*/odom']\n")
    ops.render_fleet(fleet)
    config = fleet / "server" / "server.yaml"
    assert main(["recordings", "list", "-c", str(config)]) == 0  # run from the directory
    assert "no recordings in" in capsys.readouterr().out
    (fleet / ".compose").mkdir()
    # A state file fleetctl cannot read (a damaged one): the hint is generic. With the
    # state `up` leaves, it names the deployment's URL (tests/cli/test_deploy_cli.py).
    (fleet / ".compose" / "state.json").write_text("{}\n")
    assert main(["recordings", "list", "-c", str(config)]) == ExitCode.CONFIG
    assert capsys.readouterr().err == (
        f"fleetctl: error: --config {config}: this fleet runs with `fleetctl up`, whose server "
        f"records into its data volume, not {fleet / 'server' / 'recordings'}: ask it with "
        f"--server https://HOST:9443/ --token-file FILE --ca-file "
        f"{fleet / 'server' / 'tls' / 'cert.pem'}\n")
    (fleet / "server" / "recordings").mkdir()  # a server once run from the directory itself
    assert main(["recordings", "list", "-c", str(config)]) == 0


@pytest.mark.parametrize("fmt", ["text", "json"])
def test_list_of_a_directory_that_is_not_there_is_an_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], fmt: str) -> None:
    """It used to say `no recordings in nodir` (or `[]`), exit 0: a mistyped path."""
    missing, afile = tmp_path / "nodir", tmp_path / "afile"
    afile.write_text("mine\n")
    assert main(["recordings", "list", "-d", str(missing), "-o", fmt]) == ExitCode.CONFIG
    out, err = capsys.readouterr()
    assert not out and err == f"fleetctl: error: --dir {missing}: no such directory\n"
    assert main(["recordings", "list", "-d", str(afile), "-o", fmt]) == ExitCode.CONFIG
    assert capsys.readouterr().err == f"fleetctl: error: --dir {afile}: is not a directory\n"
    assert main(["recordings", "fetch", "x.mcap", "-d", str(missing)]) == ExitCode.CONFIG
    assert f"--dir {missing}: no such directory" in capsys.readouterr().err


@pytest.mark.parametrize("command", [["list"], ["fetch", "fleet_a.mcap"]])
def test_config_dir_and_server_are_one_or_the_other(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: list[str]) -> None:
    """-c was silently ignored beside -d (and both beside --server)."""
    (tmp_path / "rec").mkdir()
    config = tmp_path / "server.yaml"
    config.write_text("auth_map: auth.yaml\n")
    for args, named in ((["-c", str(config), "-d", str(tmp_path / "rec")], "--config and --dir"),
                        (["-d", str(tmp_path), "-s", "ws://127.0.0.1:9/"], "--dir and --server"),
                        (["-c", str(config), "-s", "ws://127.0.0.1:9/"], "--config and --server")):
        to = ["--to", str(tmp_path / "out")] if command[0] == "fetch" else []
        assert main(["recordings", *command, *args, *to]) == ExitCode.USAGE
        assert capsys.readouterr().err == (f"fleetctl: error: {named} given: use one of "
                                           "--config, --dir and --server\n")
    assert not (tmp_path / "out").exists()
    # None of them (a --token-file alone): the message named only --config and --dir.
    assert main(["recordings", *command, "--token-file", str(config)]) == ExitCode.CONFIG
    assert capsys.readouterr().err == ("fleetctl: error: give --server URL (the HTTPS port, "
                                       "with --token-file and --ca-file), --config "
                                       "server.yaml or --dir DIR\n")


def test_fetch_writes_a_complete_copy_of_an_open_file(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec, out = tmp_path / "rec", tmp_path / "out"
    rec.mkdir()
    out.mkdir()
    still_open = write_recording(rec / "fleet_a.mcap", 7, close=False)
    assert main(["recordings", "fetch", "fleet_a.mcap", "--dir", str(rec), "--to", str(out),
                 "-o", "json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["messages"] == 7 and result["target"] == str(out / "fleet_a.mcap")
    assert files.is_complete(out / "fleet_a.mcap")
    with (out / "fleet_a.mcap").open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == 7
    # A second fetch to the same place and unknown names are clear errors.
    assert main(["recordings", "fetch", "fleet_a.mcap", "-d", str(rec), "--to",
                 str(out)]) == ExitCode.CONFLICT
    assert "already exists" in capsys.readouterr().err
    assert main(["recordings", "fetch", "nope.mcap", "-d", str(rec)]) != 0
    assert "no such recording" in capsys.readouterr().err
    assert main(["recordings", "fetch", "../x.mcap", "-d", str(rec)]) != 0
    still_open.close()


async def test_fetch_from_a_server_never_writes_through_a_planted_link(
        make_server: Callable[..., RelayServer], tmp_path: Path,  # noqa: F811
        capsys: pytest.CaptureFixture[str]) -> None:
    """The download went to TARGET.part opened with "wb": a symbolic link planted there
    (a shared download directory) had the recording written into the file it points to."""
    rec, out = tmp_path / "rec", tmp_path / "out"
    rec.mkdir()
    out.mkdir()
    write_recording(rec / "fleet_a.mcap", 5)
    victim = tmp_path / "victim"
    victim.write_text("precious")
    (out / "fleet_a.mcap.part").symlink_to(victim)
    (out / "fleet_b.mcap").symlink_to(tmp_path / "nowhere")  # dangling: "exists" all the same
    config = RecordingConfig(rec, (RecordingRule("/nothing"),))
    async with make_server(recording=config) as srv:
        fetched = await asyncio.to_thread(fetch_remote, Remote(srv.url, ALICE_TOKEN),
                                          "fleet_a.mcap", out)
        assert victim.read_text() == "precious"
        assert fetched.target == out / "fleet_a.mcap" and fetched.messages == 5
        assert (out / "fleet_a.mcap").read_bytes() == (rec / "fleet_a.mcap").read_bytes()
        mask = os.umask(0o022)
        os.umask(mask)
        assert stat.S_IMODE((out / "fleet_a.mcap").stat().st_mode) == 0o666 & ~mask
        assert sorted(p.name for p in out.iterdir()) == [
            "fleet_a.mcap", "fleet_a.mcap.part", "fleet_b.mcap"]  # no temp file left
        token = tmp_path / "alice.token"
        token.write_text(ALICE_TOKEN)
        token.chmod(0o600)
        remote = ["--server", srv.url, "--token-file", str(token)]
        # Exit codes as the fleet commands': conflict 4, a bad name 2, cannot write 5.
        assert main(["recordings", "fetch", "fleet_a.mcap", *remote, "--to",
                     str(out / "fleet_b.mcap")]) == ExitCode.CONFLICT
        assert "fleet_b.mcap: already exists" in capsys.readouterr().err
        assert main(["recordings", "fetch", "../fleet_a.mcap", *remote]) == ExitCode.USAGE
        # A token the fleet refuses: exit 3, as `replay` (it was 1, "failed").
        token.write_text("not-a-token")
        # (In a thread: the server answers on this test's event loop.)
        assert await asyncio.to_thread(main, ["recordings", "list", *remote]) == \
            ExitCode.CONFIG
        assert "401" in capsys.readouterr().err
        token.write_text(ALICE_TOKEN)
        assert main(["recordings", "fetch", "fleet_a.mcap", *remote, "--to",
                     str(tmp_path / "no" / "such.mcap")]) == ExitCode.ENVIRONMENT
        assert capsys.readouterr().err.endswith(
            "such.mcap: cannot write: No such file or directory\n")
    assert not (tmp_path / "no").exists()


async def test_replay_plays_a_recording_live_in_real_time(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    n, step_ns = 10, 30_000_000
    write_recording(tmp_path / "rec.mcap", n, step_ns=step_ns)
    async with make_server() as srv, client(srv, token=ALICE_TOKEN) as viewer:
        assert (await subscribe(viewer, "/ghost1/.*"))["type"] == "subscribed"
        options = ReplayOptions(srv.url, rate=1.0, token=ALICE_TOKEN, robot_name="ghost1",
                                remap=(("/husky1", "/ghost1"),))
        result = await replay(tmp_path / "rec.mcap", options)
        got = []
        while len(got) < n:
            frame = await asyncio.wait_for(viewer.recv(), 5.0)
            if isinstance(frame, bytes):
                meta, _ = default_codec().decode(frame)
                got.append((meta.topic, decode_text(frame), meta.seq, meta.publish_time_ns))
    assert result.messages == n and result.topics == {"/ghost1/chat": n}
    assert [g[:3] for g in got] == [("/ghost1/chat", f"message {i}", i + 1) for i in range(n)]
    # Real time: the frames left as far apart as the recording's log times (minus jitter),
    # stamped with the wall clock at sending.
    spread_s = (got[-1][3] - got[0][3]) / 1e9
    assert spread_s >= (n - 1) * step_ns / 1e9 * 0.9
    assert abs(got[-1][3] - time.time_ns()) < 60e9


async def test_replay_faster_than_real_time(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    write_recording(tmp_path / "rec.mcap", 20, step_ns=100_000_000)  # 1.9 s recorded
    async with make_server() as srv:
        options = ReplayOptions(srv.url, rate=None, token=ALICE_TOKEN)
        result = await replay(tmp_path / "rec.mcap", options)
        received = srv.metrics.messages_in.get("/husky1_replay/chat", 0)
    assert result.messages == 20 and received == 20
    assert result.duration_s < 1.9


async def test_replay_of_large_messages_drops_none(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    """A replay waited only on the no_drop FIFO's message bound, never its byte bound
    (64 MiB): a real 3-minute recording of the demo robot (240 kB clouds) replayed at
    --rate 0 lost 5000 of its 8381 messages and still said "replayed 8381 messages"."""
    registry = default_codec().registry
    payload = "x" * 1_000_000
    out = McapFile(tmp_path / "big.mcap", registry, 1 << 20)
    cdr = bytes(registry.typestore.serialize_cdr(registry.get(STRING).cls(payload), STRING))
    n = 72  # 72 MB: past the 64 MiB byte bound, far under the 10000-message one
    for i in range(n):
        out.write("/husky1/big", STRING, cdr, T0 + i * 1_000_000, i + 1)
    out.close()
    async with make_server() as srv:
        result = await replay(tmp_path / "big.mcap",
                              ReplayOptions(srv.url, rate=None, token=ALICE_TOKEN))
        received_bytes = srv.metrics.bytes_in.get("/husky1_replay/big", 0)
    assert result.messages == n and result.dropped == 0
    assert received_bytes >= n * len(payload)  # every message reached the server


async def test_replay_refused_by_the_send_rules_is_an_error(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    """bob may only receive /husky1/.*: the replay said "replayed 5 messages", exit 0,
    while the server had refused every one of them."""
    write_recording(tmp_path / "rec.mcap", 5, step_ns=1_000_000)
    async with make_server() as srv:
        with pytest.raises(FleetError) as caught:
            await replay(tmp_path / "rec.mcap", ReplayOptions(srv.url, rate=None,
                                                              token=BOB_TOKEN))
    assert str(caught.value) == ("replay: the server refused 1 topic(s), no send permission "
                                 "for this identity: /husky1_replay/chat (give it send "
                                 "rules, or --remap to topics it may send)")


async def test_replay_with_a_refused_token_stops_at_once(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    """A bad token was retried for 30 s, then reported as messages "still queued"."""
    write_recording(tmp_path / "rec.mcap", 5, step_ns=1_000_000)
    async with make_server() as srv:
        url, started = srv.url, time.monotonic()
        with pytest.raises(FleetError) as caught:
            await replay(tmp_path / "rec.mcap", ReplayOptions(url, rate=None,
                                                              token="not-a-token"))
    assert caught.value.exit_code == ExitCode.CONFIG
    assert str(caught.value) == (f"replay: the server {url} refused this identity: "
                                 "4401 bad token (check --token-file)")
    assert time.monotonic() - started < 20  # not the 30 s drain deadline


async def test_replay_of_a_recording_without_messages_is_an_error(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    """An empty (or cut) recording "replayed 0 messages", exit 0; a directory was "no
    such recording file"."""
    write_recording(tmp_path / "empty.mcap", 0)
    async with make_server() as srv:
        options = ReplayOptions(srv.url, rate=None, token=ALICE_TOKEN)
        with pytest.raises(FleetError, match=r"empty\.mcap: no message to replay"):
            await replay(tmp_path / "empty.mcap", options)
        (tmp_path / "no recordings").mkdir()
        with pytest.raises(FleetError, match=r"no \.mcap file in this directory"):
            await replay(tmp_path / "no recordings", options)


async def test_replay_sends_latched_topics_latched_for_late_viewers(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    """A replayed map (transient_local in the recording) went out as a plain frame: a page
    opened after it passed never got the map, nor the static TF."""
    registry = default_codec().registry
    out = McapFile(tmp_path / "rec.mcap", registry, 1024)
    cls = registry.get(STRING).cls
    for i, (topic, latched) in enumerate((("/husky1/map", True), ("/husky1/chat", False))):
        out.write(topic, STRING, bytes(registry.typestore.serialize_cdr(cls(topic), STRING)),
                  T0 + i, i + 1, latched)
    out.close()
    async with make_server() as srv:
        await replay(tmp_path / "rec.mcap", ReplayOptions(srv.url, rate=None,
                                                          token=ALICE_TOKEN))
        async with client(srv, token=ALICE_TOKEN) as late:  # after the replay ended
            assert (await subscribe(late, "/husky1_replay/.*"))["type"] == "subscribed"
            frame = await asyncio.wait_for(next_binary(late), 5.0)
    meta, _ = default_codec().decode(frame)
    # Under the replay's name (tests/cli/test_replay_live_robots.py: never husky1's own).
    assert (meta.topic, meta.latched, decode_text(frame)) == ("/husky1_replay/map", True,
                                                              "/husky1/map")


async def next_binary(ws: Any) -> bytes:
    while True:
        frame = await ws.recv()
        if isinstance(frame, bytes):
            return frame


@pytest.mark.parametrize(("qos", "latched"), [
    ("- history: keep_last\n  depth: 1\n  durability: transient_local\n", True),
    ("- history: 1\n  depth: 1\n  reliability: 1\n  durability: 1\n", True),  # Humble
    ("- history: keep_last\n  durability: volatile\n", False),
    ("", False), ("[unclosed", False), ("just text", False),
])
def test_latched_channels_are_read_from_the_rosbag2_qos(qos: str, latched: bool) -> None:
    assert is_latched({"offered_qos_profiles": qos}) is latched


def test_replay_errors_name_the_file_and_option(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "none.mcap"
    assert main(["replay", str(missing), "--server", "ws://127.0.0.1:9/"]) != 0
    assert f"{missing}: no such recording file" in capsys.readouterr().err
    assert main(["replay", str(missing), "--server", "ws://x/", "--remap",
                 "husky1=ghost"]) == ExitCode.CONFIG
    assert "--remap 'husky1=ghost'" in capsys.readouterr().err
    for remap in ("/husky1=/ghost 1", "/husky1=/ghost\n1", "/a=/$(id)", "/husky1/=/ghost1",
                  "/husky1=/gh\u00f6st"):
        # Every topic sent would have been one no ROS name can be.
        assert main(["replay", str(missing), "--server", "ws://x/", "--remap",
                     remap]) == ExitCode.CONFIG
        assert f"--remap {remap!r}: expected /old_prefix=/new_prefix, each a ROS topic " \
            "prefix" in capsys.readouterr().err
    assert main(["replay", str(missing), "--server", "ws://x/", "--rate",
                 "-1"]) == ExitCode.CONFIG
    assert main(["replay", str(missing), "--server", "ws://x/", "--robot",
                 "no spaces"]) == ExitCode.CONFIG
    assert main(["replay", str(missing), "--server", "http://x/"]) == ExitCode.CONFIG
    assert "expected a ws:// or wss:// URL" in capsys.readouterr().err
    for rate in ("nan", "inf"):
        assert main(["replay", str(missing), "--server", "ws://x/", "--rate",
                     rate]) == ExitCode.CONFIG
        assert f"--rate {rate}: must be a number >= 0" in capsys.readouterr().err
    for url, why in (("ws://[::1/", "Invalid IPv6 URL"), ("ws://x:99999/", "Port out of range"),
                     ("ws://", "hostname isn't provided")):
        assert main(["replay", str(missing), "--server", url]) == ExitCode.CONFIG
        err = capsys.readouterr().err
        assert err.startswith(f"fleetctl: error: --server {url!r}: not a URL: ") and why in err


def test_replay_command_line_with_a_token_file(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_recording(tmp_path / "rec.mcap", 5, step_ns=1_000_000)
    (tmp_path / "token").write_text(ALICE_TOKEN + "\n")
    started: dict[str, Any] = {}
    ready = threading.Event()

    async def serve() -> None:
        config = ServerConfig(listen_host="127.0.0.1", listen_port=0,
                              auth_map=tmp_path / "auth.yaml", database=None)
        stop = asyncio.Event()
        async with RelayServer(config, auth_map()) as srv:
            started.update(srv=srv, stop=stop, loop=asyncio.get_running_loop())
            ready.set()
            await stop.wait()

    thread = threading.Thread(target=asyncio.run, args=(serve(),), daemon=True)
    thread.start()
    assert ready.wait(10)
    srv = started["srv"]
    try:
        code = main(["replay", str(tmp_path / "rec.mcap"), "--server", srv.url,
                     "--token-file", str(tmp_path / "token"), "--rate", "0", "-o", "json"])
    finally:
        started["loop"].call_soon_threadsafe(started["stop"].set)
        thread.join(10)
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert result["messages"] == 5 and result["topics"] == {"/husky1_replay/chat": 5}
    assert result["renamed"] == {"/husky1": "/husky1_replay"}
    assert srv.metrics.messages_in["/husky1_replay/chat"] == 5
    assert ALICE_TOKEN not in json.dumps(result)


@pytest.mark.parametrize(("url", "expected"), [
    ("https://[::1/", "not a URL: Invalid IPv6 URL"),
    ("https://h:99999/", "not a URL: Port out of range"),
    ("x", "expected a ws://, wss://, http:// or https:// URL with a host"),
    ("https://", "expected a ws://, wss://, http:// or https:// URL with a host"),
    ("https://h:8443/?x=1", "give the server's URL without a ?query or #fragment"),
    ("https://h:8443/#top", "give the server's URL without a ?query or #fragment"),
])
def test_a_bad_server_url_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                      url: str, expected: str) -> None:
    token = tmp_path / "token"
    token.write_text("t0ken\n")
    token.chmod(0o600)
    for argv in (["recordings", "list", "-s", url, "--token-file", str(token)],
                 ["foxglove-url", "-s", url, "--token-file", str(token)]):
        if argv[0] == "foxglove-url" and not url.startswith("https://"):
            continue  # refused earlier: tickets are issued over TLS only
        assert main(argv) == ExitCode.CONFIG
        err = capsys.readouterr().err
        assert err.startswith(f"fleetctl: error: --server {url}: {expected}")
        assert "Traceback" not in err and err.count("\n") == 1


@pytest.mark.parametrize(("content", "why"), [
    (None, "No such file or directory"),
    ("not a certificate\n", "NO_CERTIFICATE_OR_CRL_FOUND"),
])
def test_a_bad_ca_file_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                   content: str | None, why: str) -> None:
    token, ca = tmp_path / "token", tmp_path / "ca.pem"
    token.write_text("t0ken\n")
    token.chmod(0o600)  # else a warning comes first on stderr
    if content is not None:
        ca.write_text(content)
    write_recording(tmp_path / "rec.mcap", 1)
    for command, url in ((["recordings", "list"], "https://127.0.0.1:9/"),
                         (["foxglove-url"], "https://127.0.0.1:9/"),
                         (["replay", str(tmp_path / "rec.mcap")], "wss://127.0.0.1:9/")):
        assert main([*command, "-s", url, "--token-file", str(token),
                     "--ca-file", str(ca)]) == ExitCode.CONFIG
        err = capsys.readouterr().err
        assert err.startswith(f"fleetctl: error: --ca-file {ca}: cannot load a CA bundle")
        assert why in err and err.count("\n") == 1


async def test_a_refused_or_missing_recording_is_said_once_with_what_to_do(
        make_server: Callable[..., RelayServer], tmp_path: Path,  # noqa: F811
        capsys: pytest.CaptureFixture[str]) -> None:
    """A wrong token said 'GET /recordings: 401 GET /recordings: the Bearer token matches
    ...' (the path twice); a file the disk bounds had deleted since it was listed said
    only '404 no recording ...'."""
    rec = tmp_path / "rec"
    rec.mkdir()
    token = tmp_path / "token"
    token.write_text("not-a-token\n")
    token.chmod(0o600)
    config = RecordingConfig(rec, (RecordingRule("/nothing"),))
    async with make_server(recording=config) as srv:
        remote = ["--server", srv.url, "--token-file", str(token)]
        assert await asyncio.to_thread(main, ["recordings", "list", *remote]) == \
            ExitCode.CONFIG
        err = capsys.readouterr().err
        assert err.startswith(f"fleetctl: error: {srv.url}: GET /recordings: 401 ") and \
            err.count("GET /recordings") == 1, err
        token.write_text(ALICE_TOKEN + "\n")
        assert await asyncio.to_thread(main, ["recordings", "fetch", "fleet_gone.mcap",
                                              *remote, "--to", str(tmp_path)]) == 1
        assert capsys.readouterr().err == (
            f"fleetctl: error: recording 'fleet_gone.mcap' is not on {srv.url} (or this "
            "token may not receive all of its topics); the server deletes the oldest files "
            "past its disk bounds: see `fleetctl recordings list`\n")


def test_a_fetch_of_the_open_file_says_it_is_a_copy_so_far(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """'wrote X (233 messages)' alone: nothing said the server was still writing it and
    the copy ended at its last flush."""
    rec = tmp_path / "rec"
    rec.mkdir()
    still_open = write_recording(rec / "fleet_a.mcap", 7, close=False)
    write_recording(rec / "fleet_b.mcap", 3)
    for name, said in (("fleet_a.mcap", "wrote {} (7 messages so far: the file is still "
                        "open (being written); this copy ends at its last flush)\n"),
                       ("fleet_b.mcap", "wrote {} (3 messages)\n")):
        assert main(["recordings", "fetch", name, "-d", str(rec), "--to", str(tmp_path)]) == 0
        assert capsys.readouterr().out == said.format(tmp_path / name)
    assert main(["recordings", "fetch", "fleet_a.mcap", "-d", str(rec), "--to",
                 str(tmp_path / "again.mcap"), "-o", "json"]) == 0
    assert json.loads(capsys.readouterr().out)["still_open"] is True
    still_open.close()
