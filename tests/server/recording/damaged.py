"""A recording with a damaged chunk, for the readers' tests (replay, files)."""

from __future__ import annotations

from pathlib import Path

from mcap.reader import make_reader
from mcap.records import ChunkIndex
from mcap.writer import CompressionType, Writer

from fleetctl.wire.codec import default_codec

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
        first = sum(1 for _ in reader.iter_messages(ending_before=chunks[0].message_end_time + 1))
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
