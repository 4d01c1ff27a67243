"""``fleetctl replay`` of a damaged recording: one line, the readable part still played."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from mcap.reader import make_reader

from fleetctl.cli.main import main
from fleetctl.cli.replay import ReplayOptions, replay
from fleetctl.errors import FleetError
from fleetctl.server.app import RelayServer
from tests.server.conftest import ALICE_TOKEN, make_server  # noqa: F401
from tests.server.recording.damaged import damage, damaged_recording


async def test_a_damaged_chunk_is_one_line_after_the_readable_messages(
        make_server: Callable[..., RelayServer], tmp_path: Path) -> None:  # noqa: F811
    # A chunk that did not decompress ended the replay with a zstandard traceback.
    first = damaged_recording(tmp_path / "rec.mcap")
    assert first > 0
    async with make_server() as srv:
        options = ReplayOptions(srv.url, rate=None, token=ALICE_TOKEN)
        with pytest.raises(FleetError) as info:
            await replay(tmp_path / "rec.mcap", options)
        received = srv.metrics.messages_in.get("/husky1/chat", 0)
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
