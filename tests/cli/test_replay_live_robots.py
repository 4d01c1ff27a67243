"""``fleetctl replay`` never drives a live robot by default: a recording's topics go out
renamed (``/husky1/goal_pose`` -> ``/husky1_replay/goal_pose``), so last week's goals
never reach the robot online now, nor its latched topics the relay's latched store;
``--onto-live-robots`` sends the recorded names, with a warning.

The live robot is a real WebSocket connection from husky1's address identity
(tests/server/conftest.py: it may receive ``/husky1/(goal_pose|initialpose)``) through a
real relay; absence is checked by a sentinel frame sent after the replay ended, which
must be the first frame the robot gets."""

from __future__ import annotations

import asyncio
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fleetctl.cli.replay import ReplayOptions, replay
from fleetctl.server.app import RelayServer
from fleetctl.server.recording.mcapfile import McapFile
from fleetctl.wire.codec import default_codec
from fleetctl.wire.control import STATUS_TYPE
from tests.cli.test_recordings import STRING, T0, next_binary, write_recording
from tests.cli.test_replay import alice_token_file
from tests.server.conftest import (  # noqa: F401
    ALICE_TOKEN,
    client,
    make_server,
    subscribe,
)
from tests.support import decode_text, string_frame

HUSKY1 = "127.0.0.2"  # husky1's address identity in the test auth map


async def _first_frame_after_sentinel(robot: Any, sender: Any, topic: str) -> bytes:
    """The first frame *robot* gets once *sender* sent a sentinel on *topic*: the
    sentinel itself when nothing replayed reached the robot."""
    await sender.send(string_frame(topic, "sentinel"))
    return await asyncio.wait_for(next_binary(robot), 5.0)


async def test_goal_poses_replayed_without_flags_never_reach_the_live_robot(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    """Replayed without --remap, every recorded topic went out under its own name: the
    robot online received last week's navigation goals and drove off."""
    write_recording(tmp_path / "rec.mcap", 3, step_ns=1_000_000, topic="/husky1/goal_pose")
    async with (make_server() as srv, client(srv, source=HUSKY1) as robot,
                client(srv, token=ALICE_TOKEN) as viewer):
        assert (await subscribe(robot, "/husky1/goal_pose"))["type"] == "subscribed"
        assert (await subscribe(viewer, "/husky1_replay/.*"))["type"] == "subscribed"
        result = await replay(tmp_path / "rec.mcap",
                              ReplayOptions(srv.url, rate=None, token=ALICE_TOKEN))
        seen = [default_codec().decode(await asyncio.wait_for(next_binary(viewer), 5.0))[0]
                for _ in range(3)]
        first = await _first_frame_after_sentinel(robot, viewer, "/husky1/goal_pose")
    assert result.topics == {"/husky1_replay/goal_pose": 3}
    assert result.renamed == {"/husky1": "/husky1_replay"}
    assert [m.topic for m in seen] == ["/husky1_replay/goal_pose"] * 3  # still watchable
    assert decode_text(first) == "sentinel"


async def test_onto_live_robots_sends_the_recorded_names(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    write_recording(tmp_path / "rec.mcap", 3, step_ns=1_000_000, topic="/husky1/goal_pose")
    async with make_server() as srv, client(srv, source=HUSKY1) as robot:
        assert (await subscribe(robot, "/husky1/goal_pose"))["type"] == "subscribed"
        result = await replay(tmp_path / "rec.mcap", ReplayOptions(
            srv.url, rate=None, token=ALICE_TOKEN, onto_live_robots=True))
        got = [decode_text(await asyncio.wait_for(next_binary(robot), 5.0)) for _ in range(3)]
    assert result.topics == {"/husky1/goal_pose": 3} and result.renamed == {}
    assert got == [f"message {i}" for i in range(3)]


async def test_a_replayed_latched_map_never_lands_in_the_live_robots_latched_store(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    """A latched topic replayed under the robot's name stayed in the relay's latched
    store: robots and pages that connected later got the old map as husky1's."""
    registry = default_codec().registry
    out = McapFile(tmp_path / "rec.mcap", registry, 1024)
    cdr = bytes(registry.typestore.serialize_cdr(registry.get(STRING).cls("old map"), STRING))
    out.write("/husky1/map", STRING, cdr, T0, 1, True)
    out.close()
    async with make_server() as srv:
        await replay(tmp_path / "rec.mcap", ReplayOptions(srv.url, rate=None,
                                                          token=ALICE_TOKEN))
        async with client(srv, token=ALICE_TOKEN) as late:
            assert (await subscribe(late, "/husky1/.*"))["type"] == "subscribed"
            first = await _first_frame_after_sentinel(late, late, "/husky1/chat")
            assert (await subscribe(late, "/husky1_replay/.*"))["type"] == "subscribed"
            replayed = await asyncio.wait_for(next_binary(late), 5.0)
    assert decode_text(first) == "sentinel"
    meta, _ = default_codec().decode(replayed)
    assert (meta.topic, meta.latched, decode_text(replayed)) == ("/husky1_replay/map", True,
                                                                 "old map")


async def _run(*args: object) -> tuple[int, str, str]:
    """``fleetctl replay ARGS`` as a user runs it, in a process of its own: exit code,
    stdout, stderr."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "fleetctl.cli.main", "replay", *map(str, args),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


async def test_the_command_says_in_one_line_where_the_topics_went(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    write_recording(tmp_path / "a.mcap", 2, step_ns=1_000_000, topic="/husky1/goal_pose")
    write_recording(tmp_path / "b.mcap", 2, step_ns=1_000_000, topic="/husky2/scan")
    token = alice_token_file(tmp_path)
    async with make_server() as srv:
        code, out, err = await _run(tmp_path / "a.mcap", "-s", srv.url, "--token-file",
                                    token, "--rate", "0", "-o", "json")
        assert code == 0, err
        assert err == ("fleetctl: warning: replay: topics renamed so that no live robot "
                       "receives them: /husky1 -> /husky1_replay (--remap OLD=NEW to choose "
                       "the names, --onto-live-robots to send the recorded ones)\n")
        assert json.loads(out)["topics"] == {"/husky1_replay/goal_pose": 2}
        # An explicit --remap is the user's choice: only the other prefixes are renamed.
        code, out, err = await _run(tmp_path / "a.mcap", "-s", srv.url, "--token-file",
                                    token, "--rate", "0", "--remap", "/husky1=/ghost1",
                                    "-o", "json")
        assert code == 0 and err == "", err
        assert json.loads(out)["topics"] == {"/ghost1/goal_pose": 2}
        code, out, err = await _run(tmp_path / "b.mcap", "-s", srv.url, "--token-file",
                                    token, "--rate", "0", "--onto-live-robots")
        assert code == 0, err
        assert err == ("fleetctl: warning: replay: --onto-live-robots: sending under the "
                       "recorded names (/husky2): a robot online that subscribes to one of "
                       "them (its goals, commands) receives and acts on it, and viewers see "
                       "its live data mixed with the replayed\n")
        assert "/husky2/scan: 2" in out
        received = srv.metrics.messages_in
    assert received.get("/husky1/goal_pose", 0) == 0
    assert received["/husky1_replay/goal_pose"] == 2 and received["/ghost1/goal_pose"] == 2


async def test_a_replayed_status_is_the_replays_robot_not_the_live_ones(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    """A replayed /husky1/status set the live husky1's registry record (status, battery,
    last seen): `status` and the page showed last week's battery as husky1's. Renamed,
    it puts the replay on the robot list as a robot of its own (`status` shows it as
    "(replay of husky1)"); the replay's session name (`--robot`, default ``replay``)
    names no robot."""
    registry = default_codec().registry
    cls = registry.get(STATUS_TYPE).cls
    out = McapFile(tmp_path / "rec.mcap", registry, 1024)
    cdr = bytes(registry.typestore.serialize_cdr(cls("docked", True, 0.25, "dock"),
                                                 STATUS_TYPE))
    out.write("/husky1/status", STATUS_TYPE, cdr, T0, 1)
    out.close()
    async with make_server() as srv:
        await replay(tmp_path / "rec.mcap", ReplayOptions(srv.url, rate=None,
                                                          token=ALICE_TOKEN))
        robots = srv.registry.as_json()
    assert [(r["name"], r["status"], r["battery_level"]) for r in robots] == [
        ("husky1_replay", "docked", 0.25)]
