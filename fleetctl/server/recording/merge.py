"""Several recordings in, one indexed MCAP file out, messages in log-time order.

Why: replicas record sharded (each replica its own senders' frames) and rotation splits a
long run into several files, so a robot that failed over from one replica to another has
its run in files of both. :func:`merge` joins them back into one file that rosbags,
``ros2 bag``, Foxglove and the ``mcap`` CLI open.

- **Order.** Each input is read through its index in log-time order (the ``mcap``
  library's seeking reader), and the inputs are merged with a heap: one pass, chunks in
  memory, not files. Inputs that follow each other in time (a replica's rotated files)
  form a lane read one after another, so the files open at once are as many as overlap
  in time (about one per replica), not one per file.
- **Channels and schemas** are deduplicated: the same topic with the same schema (name,
  encoding, text) and message encoding from two files is one channel (the first file's
  metadata); the same topic with another definition of its type is a channel of its own.
- **Selection.** ``robot``: only topics whose first segment is the robot's name
  (:func:`fleetctl.server.registry.robot_name`, the relay's own rule); ``since_ns`` and
  ``until_ns``: log times outside ``[since_ns, until_ns]`` are left out.
- **Open inputs.** A file without a footer (being written, or its writer died: a cut-short
  file looks the same) is read up to its last complete record, through a complete,
  indexed copy in *scratch* (:func:`fleetctl.server.recording.files.export`).
- **A message in two inputs is written once.** Identity: output channel, publish time,
  sequence and a digest of the data. Two ways it happens, counted apart:
  ``duplicates`` (same log time: the same frame recorded twice, e.g. a frame a robot
  sent again to its new replica after failing over because the old one had not
  acknowledged it, or a restarted worker's latched messages) and ``repeats`` (a later log
  time: the writer's copy of a latched message or of a video group at the start of a
  rotated file, whose original is in the output already, or was carried to the window's
  start: below). A copy whose original is not in the output (an earlier file not merged)
  is kept: it is what makes the merged file start with its map. Bounded: the last
  :data:`RECENT_PER_CHANNEL` messages of each channel are remembered; an exact duplicate
  is never further back than the messages sharing its log time, a start-of-file copy
  never further than its topic's messages since the original (a latched topic: its last
  one; a video group: the frames since its keyframe).
- **The window starts with what it needs from before** (``since_ns``): as a rotated file
  starts with copies of the latched messages and the video groups, the output starts
  with the newest message before ``since_ns`` of each selected latched channel, and each
  selected video channel's frames from its last keyframe before it
  (:mod:`fleetctl.server.recording.carry`; the newest over all inputs, per output
  channel), counted in ``carried``. Written as rotation writes its copies: log time the
  window's start, publish time, sequence and data the original's. A later start-of-file
  copy of a carried message is then a repeat.
"""

from __future__ import annotations

import contextlib
import hashlib
import heapq
import struct
from collections import OrderedDict
from collections.abc import Generator, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import zstandard
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Schema
from mcap.writer import CompressionType, Writer

from fleetctl.errors import FleetError
from fleetctl.server.recording import carry, files
from fleetctl.server.registry import robot_name
from fleetctl.wire.codec import default_codec

LIBRARY = "fleetctl"
RECENT_PER_CHANNEL = 4096
"""Messages remembered per output channel to recognise one written twice (about 100
bytes each)."""
_DIGEST_BYTES = 16
# What reading a damaged file raises inside the mcap library: a bad CRC or record
# (McapError), a chunk that does not decompress (zstandard; lz4: RuntimeError), a record
# cut short (struct, EOF, index errors).
_READ_ERRORS = (McapError, zstandard.ZstdError, RuntimeError, ValueError, EOFError,
                IndexError, KeyError, struct.error)


@dataclass(frozen=True)
class MergeSource:
    """One recording to merge.

    Attributes:
        path: The file on this host.
        label: How errors and the result name it (a path, or ``URL/recordings/NAME`` for a
            file fetched from a server).
        was_open: The file is a complete copy of one that was still open (a fetch).
    """

    path: Path
    label: str
    was_open: bool = False


@dataclass(frozen=True)
class Selection:
    """What of the inputs goes into the merged file.

    Attributes:
        robot: Only this robot's topics (``/NAME/...``); ``None``: every topic.
        since_ns: Earliest log time kept, ns since the epoch; ``None``: no bound.
        until_ns: Latest log time kept (inclusive); ``None``: no bound.
    """

    robot: str | None = None
    since_ns: int | None = None
    until_ns: int | None = None

    def wants(self, topic: str) -> bool:
        """Whether *topic* is selected."""
        return self.robot is None or robot_name(topic) == self.robot


@dataclass
class MergeCounts:
    """What :func:`merge` wrote.

    Attributes:
        messages: Messages written.
        duplicates: Messages left out as the same message already written with the same
            log time (recorded twice).
        repeats: Messages left out as a start-of-file copy (later log time) of a latched
            or video message already written.
        carried: Of ``messages``, those from before ``since_ns`` written at its time: the
            newest latched message of each channel, the video frames since the last
            keyframe.
        not_carried: Video topics whose frames before ``since_ns`` were not carried (no
            keyframe within :data:`fleetctl.server.recording.carry.MAX_GROUP_BYTES`).
        topics: The topics written, sorted.
        channels: Channels written.
        start_ns: Log time of the first message written (0: none).
        end_ns: Log time of the last.
        still_open: Labels of the inputs that had no footer (read up to their last
            complete record).
    """

    messages: int = 0
    duplicates: int = 0
    repeats: int = 0
    carried: int = 0
    not_carried: list[str] = field(default_factory=list)
    topics: list[str] = field(default_factory=list)
    channels: int = 0
    start_ns: int = 0
    end_ns: int = 0
    still_open: list[str] = field(default_factory=list)


def merge(sources: Sequence[MergeSource], out: BinaryIO, selection: Selection,
          scratch: Path) -> MergeCounts:
    """Write the selected messages of *sources* to *out* as one indexed MCAP file.

    Args:
        sources: The inputs; the first's header profile is the output's.
        out: Where the file goes (a new, empty file opened for binary writing).
        selection: Robot and time window.
        scratch: A directory for complete copies of open inputs (the caller removes it).

    Returns:
        The counts; ``messages`` may be 0 (the caller decides whether that is an error).

    Raises:
        FleetError: An input is missing, cannot be read, is not MCAP or is damaged (the
            message names it).
        OSError: Writing *out* failed.
    """
    counts = MergeCounts()
    inputs = [_indexed(s, scratch, n, counts) for n, s in enumerate(sources)]
    writer = Writer(out, compression=CompressionType.ZSTD)
    writer.start(profile=inputs[0].profile if inputs else "", library=LIBRARY)
    output = _Output(writer)
    if selection.since_ns is not None:
        _carry(inputs, selection, selection.since_ns, output, counts)
    with contextlib.ExitStack() as stack:
        lanes = [stack.enter_context(contextlib.closing(_in_log_time_order(lane, selection)))
                 for lane in _lanes(inputs)]
        for (_time, n), schema, channel, message in heapq.merge(*lanes, key=lambda m: m[0]):
            output.add(n, schema, channel, message, counts)
    writer.finish()  # type: ignore[no-untyped-call]
    counts.topics = sorted(output.topics)
    counts.channels = len(output.channels)
    return counts


@dataclass(frozen=True)
class _Indexed:
    """An input ready to be read through its index.

    Attributes:
        n: Its place among the inputs (ties of log time go to the earlier one).
        source: The input.
        path: The input itself, or its complete copy.
        profile: Its header's profile.
        start_ns: Log time of its first message (its summary's statistics; 0 without).
        end_ns: Of its last (the largest int64 without statistics: overlaps every input).
    """

    n: int
    source: MergeSource
    path: Path
    profile: str
    start_ns: int
    end_ns: int


def _indexed(source: MergeSource, scratch: Path, n: int, counts: MergeCounts) -> _Indexed:
    """*source* when it is complete, else a complete copy of it in *scratch*.

    Raises:
        FleetError: It is missing, not a regular file, not MCAP or damaged.
    """
    path = source.path
    if not path.is_file():
        what = "not a file" if path.exists() else "no such file"
        raise FleetError(f"{source.label}: {what}")
    try:
        complete = files.is_complete(path)
    except OSError as exc:
        raise FleetError(f"{source.label}: cannot read: {exc.strerror or exc}") from None
    if source.was_open or not complete:
        counts.still_open.append(source.label)
    found = _read_index(path, n, source) if complete else None
    if found is not None:
        return found
    copy = scratch / f"{n}{files.SUFFIX}"
    try:
        files.export(path, copy)
    except FleetError as exc:  # named by its path: name it as the caller does
        raise _renamed(exc, path, source.label) from None
    found = _read_index(copy, n, source, copy=True)
    if found is None:  # export writes a summary; reading it back failed
        raise files.DamagedRecording(f"{source.label}: cannot index a copy of it")
    return found


def _read_index(path: Path, n: int, source: MergeSource, copy: bool = False
                ) -> _Indexed | None:
    """*path*'s header and summary, or ``None`` when they cannot be read or it has no
    chunk index (a file closed with a damaged summary, or written without chunks, is then
    read as an open one: up to its last complete record); a *copy* without chunks has no
    message."""
    try:
        with path.open("rb") as stream:
            reader = SeekingReader(stream)
            profile = reader.get_header().profile
            summary = reader.get_summary()
    except (*_READ_ERRORS, OSError):
        return None
    if summary is None or not (summary.chunk_indexes or copy):
        return None
    stats = summary.statistics
    if stats is None:
        return _Indexed(n, source, path, profile, 0, _NO_END)
    return _Indexed(n, source, path, profile, stats.message_start_time,
                    stats.message_end_time)


_NO_END = 2**63 - 1


def _lanes(inputs: list[_Indexed]) -> list[list[_Indexed]]:
    """The inputs in chains whose time ranges do not overlap, each chain in time order:
    a chain is read one file after another, so the files open at once (and the chunks in
    memory) are as many as overlap in time (about one per replica), not one per file."""
    lanes: list[list[_Indexed]] = []
    for each in sorted(inputs, key=lambda i: (i.start_ns, i.n)):
        lane = next((lane for lane in lanes if lane[-1].end_ns <= each.start_ns), None)
        if lane is None:
            lanes.append([each])
        else:
            lane.append(each)
    return lanes


def _renamed(exc: FleetError, path: Path, label: str) -> FleetError:
    message = str(exc)
    if message.startswith(str(path)):
        message = label + message[len(str(path)):]
    return type(exc)(message, exit_code=exc.exit_code)


_Item = tuple[tuple[int, int], Schema | None, Channel, Message]


def _in_log_time_order(lane: list[_Indexed], selection: Selection
                       ) -> Generator[_Item, None, None]:
    """The selected messages of a lane's inputs in log-time order, keyed for the heap.

    Raises:
        FleetError: An input is damaged (the messages before the damage were yielded).
    """
    for each in lane:
        with _reading(each) as stream:
            yield from _ordered(stream, each.n, selection)


@contextlib.contextmanager
def _reading(each: _Indexed) -> Iterator[BinaryIO]:
    """*each* open for reading; what reading it raises as an error naming it.

    Raises:
        FleetError: It is damaged.
    """
    try:
        with each.path.open("rb") as stream:
            yield stream
    except (*_READ_ERRORS, OSError) as exc:
        raise files.DamagedRecording(f"{each.source.label}: damaged data, cannot merge "
                                     f"it ({type(exc).__name__}: {exc})") from None


def _ordered(stream: BinaryIO, n: int, selection: Selection) -> Iterator[_Item]:
    reader = SeekingReader(stream, validate_crcs=True)
    summary = reader.get_summary()
    if summary is None:
        return
    topics = sorted({c.topic for c in summary.channels.values() if selection.wants(c.topic)})
    if not topics:
        return
    for schema, channel, message in reader.iter_messages(
            topics=topics, starting_at=selection.since_ns, ending_at=selection.until_ns):
        yield (message.log_time, n), schema, channel, message


def _carry(inputs: list[_Indexed], selection: Selection, since_ns: int, output: _Output,
           counts: MergeCounts) -> None:
    """Write at *since_ns* what the window needs from before it (the module's docstring):
    per output channel, the newest found over the inputs (ties: the earlier input).

    Raises:
        FleetError: An input is damaged.
    """
    best: dict[_ChannelKey, tuple[int, carry.CarriedChannel]] = {}
    not_carried: set[str] = set()
    for each in inputs:
        if each.start_ns >= since_ns:  # nothing before the window (its statistics)
            continue
        with _reading(each) as stream:
            found = carry.before(stream, since_ns, selection.wants, _deserializer)
        not_carried |= found.not_carried
        for channel in found.carried.values():
            key = _channel_key(channel.schema, channel.channel)
            held = best.get(key)
            if held is None or channel.newest_ns > held[1].newest_ns:
                best[key] = (each.n, channel)
    # A video topic carried from one input is carried, whatever another input lacked.
    carried_topics = {c.channel.topic for _n, c in best.values()}
    counts.not_carried = sorted(not_carried - carried_topics)
    for n, channel in sorted(best.values(), key=lambda b: (b[1].messages[0].log_time, b[0])):
        for message in channel.messages:
            if output.add(n, channel.schema, channel.channel, message, counts, since_ns):
                counts.carried += 1


def _deserializer() -> carry.Deserialize:
    # The recorder writes video with the default registry's definition (its schema).
    return default_codec().registry.typestore.deserialize_cdr


_SchemaKey = tuple[str, str, bytes]
_ChannelKey = tuple[str, str, _SchemaKey | None]


def _channel_key(schema: Schema | None, channel: Channel) -> _ChannelKey:
    """What makes two inputs' channels one output channel: topic, message encoding and
    schema (name, encoding, text)."""
    schema_key = (schema.name, schema.encoding, schema.data) if schema else None
    return (channel.topic, channel.message_encoding, schema_key)


class _Output:
    """The merged file's schemas, channels and recently written messages."""

    def __init__(self, writer: Writer) -> None:
        self._writer = writer
        self._schemas: dict[_SchemaKey, int] = {}
        self.channels: dict[_ChannelKey, int] = {}
        self._by_input: dict[tuple[int, int], int] = {}  # (input, its channel id) -> ours
        self.topics: set[str] = set()
        # Per output channel: (publish time, sequence, digest) -> log time, oldest first.
        self._recent: dict[int, OrderedDict[tuple[int, int, bytes], int]] = {}

    def add(self, n: int, schema: Schema | None, channel: Channel, message: Message,
            counts: MergeCounts, log_time: int | None = None) -> bool:
        """Write *message* of input *n* unless it was written already (counted); at
        *log_time* (a carried message), ``None``: its own. Returns whether it was
        written."""
        log_time = message.log_time if log_time is None else log_time
        out_channel = self._by_input.get((n, channel.id))
        if out_channel is None:
            out_channel = self._by_input[(n, channel.id)] = self._channel(schema, channel)
        recent = self._recent.setdefault(out_channel, OrderedDict())
        key = (message.publish_time, message.sequence,
               hashlib.blake2b(message.data, digest_size=_DIGEST_BYTES).digest())
        seen_at = recent.get(key)
        if seen_at is not None:
            if seen_at == log_time:
                counts.duplicates += 1
            else:
                counts.repeats += 1
            return False
        recent[key] = log_time
        if len(recent) > RECENT_PER_CHANNEL:
            recent.popitem(last=False)
        self._writer.add_message(out_channel, log_time, message.data,
                                 message.publish_time, message.sequence)
        if not counts.messages:
            counts.start_ns = log_time
        counts.messages += 1
        counts.end_ns = log_time
        return True

    def _channel(self, schema: Schema | None, channel: Channel) -> int:
        key = _channel_key(schema, channel)
        found = self.channels.get(key)
        if found is not None:
            return found
        schema_id = 0  # MCAP: no schema
        schema_key = key[2]
        if schema is not None and schema_key is not None:
            schema_id = self._schemas.get(schema_key, 0)
            if not schema_id:
                schema_id = self._writer.register_schema(schema.name, schema.encoding,
                                                         schema.data)
                self._schemas[schema_key] = schema_id
        found = self._writer.register_channel(channel.topic, channel.message_encoding,
                                              schema_id, channel.metadata)
        self.channels[key] = found
        self.topics.add(channel.topic)
        return found
