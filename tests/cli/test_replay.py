"""``fleetctl replay`` of a damaged recording: one line, the readable part still played."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import ChunkIndex
from mcap.writer import CompressionType, Writer

from fleetctl.cli.main import main
from fleetctl.cli.replay import ReplayOptions, replay
from fleetctl.errors import FleetError
from fleetctl.server.app import RelayServer
from fleetctl.wire.codec import default_codec
from tests.server.conftest import ALICE_TOKEN, make_server  # noqa: F401

STRING = "std_msgs/msg/String"
T0 = 1_700_000_000_000_000_000


def damaged_recording(path: Path, n: int = 300) -> int:
    """A zstd-chunked recording of *n* Strings whose second chunk is overwritten with
    junk; returns how many messages the first chunk holds."""
    registry = default_codec().registry
    cls = registry.get(STRING).cls
    with path.open("wb") as f:
        w = Writer(f, chunk_size=2048, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="test")
        schema = w.register_schema(name=STRING, encoding="ros2msg", data=b"string data")
        channel = w.register_channel(topic="/husky1/chat", message_encoding="cdr",
                                     schema_id=schema)
        for i in range(n):
            cdr = bytes(registry.typestore.serialize_cdr(cls(f"message {i:04d} " * 4), STRING))
            w.add_message(channel_id=channel, log_time=T0 + i, publish_time=T0 + i, data=cdr,
                          sequence=i)
        w.finish()
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
        assert len(chunks) >= 3
        first = sum(1 for _ in reader.iter_messages(end_time=chunks[0].message_end_time + 1))
    damage(path, chunks[1])
    return first


# Opcode, record length, start and end times, uncompressed size and CRC, "zstd", length:
# the zstd frame (and its magic number, which every damage here overwrites) starts here.
ZSTD_FRAME_AT = 1 + 8 + 8 + 8 + 8 + 4 + (4 + 4) + 8


def damage(path: Path, chunk: ChunkIndex) -> None:
    """Overwrite the start of *chunk*'s zstd frame (damage inside it may go unnoticed:
    zstd frames carry no checksum here)."""
    data = bytearray(path.read_bytes())
    start = chunk.chunk_start_offset + ZSTD_FRAME_AT
    data[start:start + 8] = b"\xa5" * 8
    path.write_bytes(bytes(data))


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
