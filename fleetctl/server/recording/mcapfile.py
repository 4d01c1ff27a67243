"""One rosbag2-compatible MCAP file being written (MCAP spec; rosbag2_storage_mcap).

What makes it rosbag2's: header profile ``ros2``; one schema per type, named
``pkg/msg/Type``, encoding ``ros2msg``, data the full ``.msg`` text with dependencies
(:func:`fleetctl.wire.ros2msg.schema_text`); one channel per (topic, type), encoding
``cdr``, with the channel metadata rosbag2 writes (``offered_qos_profiles`` as YAML and
``topic_type_hash``); log time and publish time are the robot's publish time.

Readable while open: :meth:`McapFile.flush` closes the chunk in progress and writes it out,
so the file on disk always ends at a record boundary and a reader that stops at the end of
the data (:func:`fleetctl.server.recording.files.read_messages`) sees every message up to the
last flush. :meth:`McapFile.close` writes the summary and footer.

Not thread-safe: the recorder's writer thread owns its files.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import BinaryIO

from mcap.writer import CompressionType, Writer

from fleetctl.wire.registry import TypeRegistry
from fleetctl.wire.ros2msg import MESSAGE_ENCODING, SCHEMA_ENCODING, schema_text, type_hash

PROFILE = "ros2"
LIBRARY = "fleetctl"
# Bytes a message record adds to its payload (opcode, length, channel, sequence, two
# timestamps) plus its message index entry: for the size estimate between flushes.
_MESSAGE_OVERHEAD_BYTES = 9 + 2 + 4 + 8 + 8 + 16
# rosbag2's offered QoS of a topic (ROS 2 Jazzy key names); durations are "infinite"
# (RMW_DURATION_INFINITE, INT64_MAX ns). Latched topics are transient_local.
_INFINITE = "{sec: 9223372036, nsec: 854775807}"
_QOS = ("- history: keep_last\n  depth: 10\n  reliability: reliable\n  durability: %s\n"
        f"  deadline: {_INFINITE}\n  lifespan: {_INFINITE}\n  liveliness: automatic\n"
        f"  liveliness_lease_duration: {_INFINITE}\n  avoid_ros_namespace_conventions: false\n")


class McapFile:
    """An MCAP file open for writing.

    Args:
        path: Where to create it (must not exist).
        registry: Defines the types written.
        chunk_bytes: Uncompressed chunk size before a chunk is written out.
    """

    def __init__(self, path: Path, registry: TypeRegistry, chunk_bytes: int) -> None:
        self.path = path
        self.registry = registry
        self._stream: BinaryIO = path.open("xb")
        self._writer = Writer(self._stream, chunk_size=chunk_bytes,
                              compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._stream.flush()  # a reader of the new file sees an MCAP header at once
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._unflushed_bytes = 0
        self.messages = 0
        self.topics: set[str] = set()

    @property
    def size_bytes(self) -> int:
        """Bytes on disk plus an estimate of the chunk in progress (uncompressed)."""
        return self._stream.tell() + self._unflushed_bytes

    def write(self, topic: str, type_name: str, cdr: bytes, time_ns: int, seq: int,
              latched: bool = False, publish_time_ns: int | None = None) -> None:
        """Append one message.

        Args:
            topic: Its topic.
            type_name: Its ROS 2 type (``pkg/msg/Type``).
            cdr: The CDR payload.
            time_ns: Log and publish time, ns since the epoch.
            seq: The sender's sequence number (kept modulo 2**32, MCAP's field width).
            latched: The topic is latched (its channel's QoS says transient_local).
            publish_time_ns: Publish time when it differs from *time_ns* (a latched
                message written again at the start of a new file); None: *time_ns*.

        Raises:
            WireError: The type has no schema in the registry.
            OSError: Writing failed.
        """
        channel = self._channels.get((topic, type_name))
        if channel is None:
            channel = self._channel(topic, type_name, latched)
        published = time_ns if publish_time_ns is None else publish_time_ns
        self._writer.add_message(channel, log_time=time_ns, data=cdr, publish_time=published,
                                 sequence=seq & 0xFFFFFFFF)
        self._unflushed_bytes += len(cdr) + _MESSAGE_OVERHEAD_BYTES
        self.messages += 1

    def flush(self) -> None:
        """Write out the chunk in progress and flush the file (no fsync).

        Raises:
            OSError: Writing failed.
        """
        self._writer.flush()  # type: ignore[no-untyped-call]
        self._unflushed_bytes = 0

    def close(self) -> None:
        """Write the summary and footer and close the file.

        Raises:
            OSError: Writing failed (the file is closed anyway).
        """
        try:
            self._writer.finish()  # type: ignore[no-untyped-call]
        finally:
            self._stream.close()

    def abandon(self) -> None:
        """Close the file without a summary (after a write error); what is on disk stays
        readable up to the last complete record."""
        with contextlib.suppress(OSError):
            self._stream.close()

    def _channel(self, topic: str, type_name: str, latched: bool) -> int:
        schema = self._schemas.get(type_name)
        if schema is None:
            text = schema_text(self.registry, type_name)
            schema = self._writer.register_schema(type_name, SCHEMA_ENCODING, text.encode())
            self._schemas[type_name] = schema
        metadata = {
            "offered_qos_profiles": _QOS % ("transient_local" if latched else "volatile"),
            "topic_type_hash": type_hash(self.registry, type_name),
        }
        channel: int = self._writer.register_channel(topic, MESSAGE_ENCODING, schema, metadata)
        self._channels[(topic, type_name)] = channel
        self.topics.add(topic)
        return channel
