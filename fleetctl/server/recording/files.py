"""The recording directory: file names, listing, reading open files, disk bounds.

Files are named ``fleet_<UTC start>.mcap`` (``fleet_20261125T133400Z.mcap``; ``-1``,
``-2``... when a name is taken), so names sort by start time. A file without a footer is
still being written, or its writer died; :func:`read_messages` reads either up to its last
complete record, and :func:`export` turns it into a complete, indexed file.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import stat
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zstandard
from mcap.exceptions import InvalidMagic, McapError
from mcap.reader import make_reader
from mcap.records import Channel, Footer, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from fleetctl.errors import FleetError

SUFFIX = ".mcap"
PREFIX = "fleet_"
# Bytes at the end of a complete MCAP file: the footer record and the magic.
_TAIL_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class RecordingFile:
    """One ``.mcap`` file of the directory.

    Attributes:
        name: File name (no directory).
        path: Full path.
        size_bytes: Size on disk.
        modified_s: Last write, seconds since the epoch.
    """

    name: str
    path: Path
    size_bytes: int
    modified_s: float


def new_path(directory: Path, now_s: float, label: str | None = None) -> Path:
    """A free file name for a recording started at *now_s* (seconds since the epoch);
    *label* (a replica's name: ``A-Z a-z 0-9 _ -``) goes in front of the time."""
    stamp = dt.datetime.fromtimestamp(now_s, dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    base = f"{PREFIX}{label}_{stamp}" if label else f"{PREFIX}{stamp}"
    path = directory / f"{base}{SUFFIX}"
    n = 0
    while path.exists():
        n += 1
        path = directory / f"{base}-{n}{SUFFIX}"
    return path


def scan(directory: Path) -> list[RecordingFile]:
    """The ``.mcap`` files of *directory*, oldest (last write) first; a missing directory
    has none. Files that vanish while scanning, and entries that are not regular files
    (a directory named ``x.mcap``), are skipped.

    Raises:
        FleetError: *directory* is not a directory.
    """
    found = []
    try:
        entries = list(directory.iterdir())
    except FileNotFoundError:
        return []
    except NotADirectoryError:
        raise FleetError(f"{directory}: not a directory") from None
    for entry in entries:
        if entry.suffix != SUFFIX:
            continue
        try:
            st = entry.stat()
        except FileNotFoundError:
            continue
        if not stat.S_ISREG(st.st_mode):
            continue
        found.append(RecordingFile(entry.name, entry, st.st_size, st.st_mtime))
    return sorted(found, key=lambda f: (f.modified_s, f.name))


def is_complete(path: Path) -> bool:
    """Whether *path* ends with MCAP's closing magic (its writer finished it)."""
    with path.open("rb") as stream:
        stream.seek(0, 2)
        if stream.tell() < 2 * len(_TAIL_MAGIC):
            return False
        stream.seek(-len(_TAIL_MAGIC), 2)
        return stream.read() == _TAIL_MAGIC


class DamagedRecording(FleetError):
    """A record of the file cannot be decoded (a chunk that does not decompress); the
    message says why. The messages before it were read."""


# What mcap's chunk decompression raises on damaged data: zstandard's error, and lz4's
# RuntimeError ("LZ4F_... failed"). A cut-short chunk raises the EOF/struct errors instead.
_DECOMPRESS_ERRORS = (zstandard.ZstdError, RuntimeError)


def read_messages(path: Path) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """Every message of *path* in file order, complete or not.

    A file still being written (or whose writer died) is read up to its last complete
    record; the partial record after it, if any, is ignored.

    Raises:
        DamagedRecording: A chunk cannot be decompressed (what came before it was
            yielded).
        FleetError: *path* cannot be read or is not MCAP.
    """
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    try:
        with path.open("rb") as stream:
            for record in _tolerant_records(stream):
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message) and record.channel_id in channels:
                    channel = channels[record.channel_id]
                    yield schemas.get(channel.schema_id), channel, record
    except OSError as exc:
        raise FleetError(f"{path}: cannot read: {exc.strerror or exc}") from None


def _tolerant_records(stream: Any) -> Iterator[Any]:
    head = stream.read(len(_TAIL_MAGIC))
    if not _TAIL_MAGIC.startswith(head) and len(head) < len(_TAIL_MAGIC):
        # Too short for the reader's own magic check (it fails with struct.error).
        raise FleetError(f"{getattr(stream, 'name', '?')}: not an MCAP file")
    stream.seek(0)
    reader = StreamReader(stream, skip_magic=False)
    try:
        for record in reader.records:
            if isinstance(record, Footer):
                return
            yield record
    except InvalidMagic:
        raise FleetError(f"{getattr(stream, 'name', '?')}: not an MCAP file") from None
    except McapError:
        return  # the end of what was written so far (an empty file: nothing yet)
    except (EOFError, ValueError, IndexError, KeyError, AttributeError, struct.error):
        return  # a record cut short by the end of the data (zstd frame, struct unpack)
    except _DECOMPRESS_ERRORS as exc:  # damage, not an end: was a zstandard traceback
        raise DamagedRecording(f"{getattr(stream, 'name', '?')}: damaged data, the rest of "
                               f"the file cannot be read ({type(exc).__name__}: {exc})"
                               ) from None


def describe(path: Path) -> dict[str, Any]:
    """A JSON-ready summary of *path*: messages, start/end (ns), topics, complete.

    A complete file is described from its summary section; an open one by reading it.

    Raises:
        FleetError: The file cannot be read or is not MCAP.
    """
    complete = is_complete(path)
    if complete:
        try:
            with path.open("rb") as stream:
                summary = make_reader(stream).get_summary()
        except (McapError, OSError, ValueError) as exc:
            raise FleetError(f"{path}: cannot read its summary: {exc}") from None
        if summary is not None and summary.statistics is not None:
            stats = summary.statistics
            return {"complete": True, "messages": stats.message_count,
                    "start_ns": stats.message_start_time, "end_ns": stats.message_end_time,
                    "topics": sorted({c.topic for c in summary.channels.values()})}
    count, start, end, topics = 0, 0, 0, set()
    for _schema, channel, message in read_messages(path):
        count += 1
        start = message.log_time if count == 1 else min(start, message.log_time)
        end = max(end, message.log_time)
        topics.add(channel.topic)
    return {"complete": complete, "messages": count, "start_ns": start, "end_ns": end,
            "topics": sorted(topics)}


def export(source: Path, target: Path) -> int:
    """Write a complete, indexed copy of *source* (open or not) to *target*.

    Returns:
        Messages copied.

    Raises:
        FleetError: *source* cannot be read, or *target* exists or cannot be written.
    """
    try:
        out = target.open("xb")
    except OSError as exc:
        raise FleetError(f"{target}: cannot create: {exc.strerror or exc}") from None
    with out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="fleetctl")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        count = 0
        for schema, channel, message in read_messages(source):
            if channel.id not in channel_ids:
                sid = 0
                if schema is not None:
                    if schema.id not in schema_ids:
                        schema_ids[schema.id] = writer.register_schema(
                            schema.name, schema.encoding, schema.data)
                    sid = schema_ids[schema.id]
                channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, sid, channel.metadata)
            writer.add_message(channel_ids[channel.id], message.log_time, message.data,
                               message.publish_time, message.sequence)
            count += 1
        writer.finish()  # type: ignore[no-untyped-call]
    return count


def enforce_bounds(directory: Path, current: Path | None, keep_bytes: int,
                   max_age_s: float | None, now_s: float | None = None,
                   ) -> list[tuple[RecordingFile, str]]:
    """Delete closed files past the bounds, oldest first.

    Args:
        directory: The recording directory.
        current: The file being written (never deleted), or ``None``.
        keep_bytes: Closed files together must fit in this many bytes.
        max_age_s: Closed files last written longer ago than this are deleted; ``None``:
            no age bound.
        now_s: Wall clock, seconds since the epoch (default: now).

    Returns:
        The deleted files, each with its reason (``max_age`` or ``max_total_bytes``).
    """
    now_s = time.time() if now_s is None else now_s
    closed = [f for f in scan(directory) if f.path != current]
    deleted: list[tuple[RecordingFile, str]] = []
    total = sum(f.size_bytes for f in closed)
    for f in closed:
        reason = None
        if max_age_s is not None and f.modified_s < now_s - max_age_s:
            reason = "max_age"
        elif total > keep_bytes:
            reason = "max_total_bytes"
        if reason is None:
            continue
        with contextlib.suppress(FileNotFoundError):
            f.path.unlink()
        total -= f.size_bytes
        deleted.append((f, reason))
    return deleted
