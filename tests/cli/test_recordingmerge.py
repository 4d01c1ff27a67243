"""``fleetctl recordings merge`` on this host (``--dir``, paths): inputs, output file,
errors and exit codes; the merge itself is tests/server/recording/test_merge.py."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest
from rosbags.highlevel import AnyReader

from fleetctl.cli.main import main
from fleetctl.cli.recordingmerge import parse_time, selected_remote
from fleetctl.cli.recordings import RemoteRecording
from fleetctl.errors import ExitCode, FleetError
from fleetctl.server.recording.mcapfile import McapFile
from fleetctl.server.recording.merge import Selection
from fleetctl.wire.codec import default_codec
from tests.cli.test_recordings import STRING, T0, write_recording
from tests.server.recording.damaged import damaged_recording

MS = 1_000_000
STEP_NS = 20 * MS


def test_times_are_epoch_seconds_or_iso_8601_in_utc() -> None:
    assert parse_time("1700000000", "--since") == T0
    assert parse_time("1700000000.25", "--since") == T0 + 250 * MS
    assert parse_time("2023-11-14T22:13:20Z", "--since") == T0
    assert parse_time("2023-11-14 22:13:20.5", "--since") == T0 + 500 * MS  # no offset: UTC
    assert parse_time("2023-11-14T23:13:20+01:00", "--since") == T0
    with pytest.raises(FleetError, match=r"^--until 'yesterday': not a time") as raised:
        parse_time("yesterday", "--until")
    assert raised.value.exit_code == ExitCode.USAGE


def listed(name: str, topics: list[str], modified_s: float) -> RemoteRecording:
    return RemoteRecording(name, 1, modified_s, True, topics)


def test_a_listed_file_is_fetched_when_it_may_hold_the_selection() -> None:
    name = "fleet_relay-a_20231114T221320Z.mcap"  # started at T0
    start_s = T0 // 1_000_000_000
    one = listed(name, ["/husky1/chat"], start_s + 3600)
    assert selected_remote(one, Selection("husky1"))
    assert not selected_remote(one, Selection("husky2"))
    assert not selected_remote(listed(name, ["/status"], 0), Selection("husky1"))
    hour_ns = 3600 * 1_000_000_000
    # Last written an hour after T0: nothing logged two hours after it (with the slack).
    assert not selected_remote(one, Selection(since_ns=T0 + 2 * hour_ns))
    assert selected_remote(one, Selection(since_ns=T0 + hour_ns + 300 * 1_000_000_000))
    # Started at T0 (its name): nothing logged an hour before.
    assert not selected_remote(one, Selection(until_ns=T0 - hour_ns))
    assert selected_remote(one, Selection(until_ns=T0 - 300 * 1_000_000_000))
    assert selected_remote(listed("other.mcap", ["/husky1/x"], start_s), Selection(
        until_ns=T0 - hour_ns))  # no time in its name: fetched


def two_robots(directory: Path) -> None:
    """Two closed files and an open one, husky1 and husky2 interleaved in log time."""
    directory.mkdir()
    write_recording(directory / "fleet_relay-a_1.mcap", 5, step_ns=2 * STEP_NS)
    write_recording(directory / "fleet_relay-b_1.mcap", 5, step_ns=2 * STEP_NS,
                    topic="/husky2/chat")
    still_open = write_recording(directory / "fleet_relay-b_2.mcap", 3, step_ns=2 * STEP_NS,
                                 close=False)
    still_open._stream.close()  # as a writer that died: no footer


def topics_and_times(path: Path) -> list[tuple[str, int]]:
    with AnyReader([path]) as reader:
        return [(c.topic, (t - T0) // MS) for c, t, _ in reader.messages()]


def test_merge_from_a_directory_by_robot(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    two_robots(tmp_path / "rec")
    out = tmp_path / "husky1.mcap"
    argv = ["recordings", "merge", "--dir", str(tmp_path / "rec"), "--robot", "husky1",
            "--to", str(out), "-o", "json"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    # relay-b_2 holds the same 3 first messages as relay-a_1 (same times and data).
    assert (result["files"], result["messages"], result["duplicates"]) == (2, 5, 3)
    assert result["topics"] == ["/husky1/chat"]
    assert (result["start_ns"], result["end_ns"]) == (T0, T0 + 8 * STEP_NS)
    assert [Path(s).name for s in result["still_open"]] == ["fleet_relay-b_2.mcap"]
    assert topics_and_times(out) == [("/husky1/chat", ms) for ms in range(0, 161, 40)]
    assert stat.S_IMODE(out.stat().st_mode) == 0o644
    assert sorted(p.name for p in tmp_path.iterdir()) == ["husky1.mcap", "rec"]  # no temp


def test_merge_paths_with_a_window_and_the_text_result(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    two_robots(tmp_path / "rec")
    out = tmp_path / "window.mcap"
    paths = [str(tmp_path / "rec" / n) for n in ("fleet_relay-a_1.mcap",
                                                   "fleet_relay-b_1.mcap")]
    assert main(["recordings", "merge", *paths, "--since", "1700000000.04",
                 "--until", "1700000000.12", "--to", str(out)]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"wrote {out}: 6 messages on 2 topic(s), 2023-11-14 22:13:20.040 "
                           "to 2023-11-14 22:13:20.120 UTC, from 2 recording(s)")
    assert topics_and_times(out) == [(f"/husky{n}/chat", ms) for ms in (40, 80, 120)
                                     for n in (1, 2)]


def test_an_existing_output_is_replaced_only_with_force(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    two_robots(tmp_path / "rec")
    out = tmp_path / "out.mcap"
    out.write_text("keep me")
    argv = ["recordings", "merge", "-d", str(tmp_path / "rec"), "--to", str(out)]
    assert main(argv) == ExitCode.CONFLICT
    assert f"{out}: already exists (give --force" in capsys.readouterr().err
    assert out.read_text() == "keep me"
    assert main([*argv, "--force"]) == 0
    assert len(topics_and_times(out)) == 10
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap", "rec"]


@pytest.mark.parametrize(("argv", "code", "said"), [
    ([], ExitCode.USAGE, "give the recordings to merge"),
    (["x.mcap", "--since", "soon"], ExitCode.USAGE, "--since 'soon': not a time"),
    (["x.mcap", "--since", "20", "--until", "10"], ExitCode.USAGE, "is before --since"),
    (["x.mcap", "--robot", "a/b"], ExitCode.USAGE, "--robot 'a/b': give a robot's name"),
    (["x.mcap", "-d", "D", "-s", "http://127.0.0.1:1/"], ExitCode.USAGE,
     "--dir and --server given"),
    (["-d", "D", "../x.mcap"], ExitCode.USAGE, "recording name '../x.mcap'"),
])
def test_usage_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                      monkeypatch: pytest.MonkeyPatch, argv: list[str],
                      code: ExitCode, said: str) -> None:
    (tmp_path / "D").mkdir()
    # monkeypatch's chdir goes back after the test: os.chdir left every later test in this
    # directory, and those that start `python -m tests...` (test_bridge, test_qos) failed.
    monkeypatch.chdir(tmp_path)
    assert main(["recordings", "merge", *argv, "--to", str(tmp_path / "o.mcap")]) == code
    err = capsys.readouterr().err
    assert said in err and "Traceback" not in err
    assert not (tmp_path / "o.mcap").exists()


def test_the_merged_file_is_not_written_into_the_directory_it_merges(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """There the relay's retention would count and delete it, and the next merge of the
    directory would read it again."""
    two_robots(tmp_path / "rec")
    monkeypatch.chdir(tmp_path / "rec")
    for to in (tmp_path / "rec" / "merged.mcap", Path("merged.mcap")):
        assert main(["recordings", "merge", "--dir", str(tmp_path / "rec"),
                     "--to", str(to)]) == ExitCode.USAGE
        err = capsys.readouterr().err
        assert f"--to {to}: is in the recording directory {tmp_path / 'rec'}" in err
        assert "write it elsewhere" in err and "Traceback" not in err
    assert not (tmp_path / "rec" / "merged.mcap").exists()
    assert main(["recordings", "merge", "--dir", ".", "--to", "../merged.mcap"]) == 0
    assert len(topics_and_times(tmp_path / "merged.mcap")) == 10


def test_bad_inputs_are_named_and_leave_nothing_behind(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    two_robots(tmp_path / "rec")
    good = str(tmp_path / "rec" / "fleet_relay-a_1.mcap")
    (tmp_path / "notes.mcap").write_text("these are notes, not a recording")
    damaged_recording(tmp_path / "damaged.mcap")
    out = tmp_path / "out" / "o.mcap"
    out.parent.mkdir()
    cases = [
        ([good, str(tmp_path / "gone.mcap")], f"{tmp_path / 'gone.mcap'}: no such file"),
        ([good, str(tmp_path / "notes.mcap")], f"{tmp_path / 'notes.mcap'}: not an MCAP file"),
        ([str(tmp_path / "damaged.mcap")], f"{tmp_path / 'damaged.mcap'}: damaged data"),
        ([good, "--robot", "husky9"], "no message of robot 'husky9' (topics /husky9/...) in"),
        (["-d", str(tmp_path / "rec"), "--robot", "husky9"],
         "no recording of robot 'husky9'"),
        ([good, "--since", "2030-01-01"], "no message since 2030-01-01 00:00:00.000 UTC in"),
    ]
    for args, said in cases:
        assert main(["recordings", "merge", *args, "--to", str(out)]) == ExitCode.FAILURE
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err, (args, err)
        assert list(out.parent.iterdir()) == []  # no output, no temp file, no scratch
    nowhere = tmp_path / "nowhere" / "o.mcap"
    assert main(["recordings", "merge", good, "--to", str(nowhere)]) == ExitCode.ENVIRONMENT
    assert f"{nowhere}: cannot write: no such directory" in capsys.readouterr().err
    assert main(["recordings", "merge", good, "--to", str(tmp_path)]) == ExitCode.USAGE
    assert "is a directory" in capsys.readouterr().err


def with_a_map(path: Path) -> None:
    """A map sent once (latched, twice updated), then chat every 20 ms until 100 ms."""
    registry = default_codec().registry
    out = McapFile(path, registry, 1024)
    for i, (topic, text, latched) in enumerate(
            [("/husky1/map", "map v1", True), ("/husky1/map", "map v2", True)]
            + [("/husky1/chat", f"chat {n}", False) for n in range(4)]):
        cdr = bytes(registry.typestore.serialize_cdr(registry.get(STRING).cls(text), STRING))
        out.write(topic, STRING, cdr, T0 + i * STEP_NS, i + 1, latched)
    out.close()


def test_a_window_starts_with_the_latched_map_from_before_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with_a_map(tmp_path / "in.mcap")
    out = tmp_path / "window.mcap"
    argv = ["recordings", "merge", str(tmp_path / "in.mcap"), "--since", "1700000000.07",
            "--to", str(out)]
    assert main([*argv, "-o", "json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert (result["messages"], result["carried"], result["not_carried"]) == (3, 1, [])
    with AnyReader([out]) as reader:
        assert [(c.topic, (t - T0) // MS, reader.deserialize(raw, c.msgtype).data)
                for c, t, raw in reader.messages()] == [
            ("/husky1/map", 70, "map v2"), ("/husky1/chat", 80, "chat 2"),
            ("/husky1/chat", 100, "chat 3")]
    assert main([*argv, "--force"]) == 0
    assert "  carried: 1 message(s) from before --since" in capsys.readouterr().out
    # A window after the last message: the map alone is no window.
    argv = ["recordings", "merge", str(tmp_path / "in.mcap"), "--since", "1700000000.5",
            "--to", str(tmp_path / "late.mcap")]
    assert main(argv) == ExitCode.FAILURE
    assert "no message since 2023-11-14 22:13:20.500 UTC in" in capsys.readouterr().err
    assert not (tmp_path / "late.mcap").exists()
