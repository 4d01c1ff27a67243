"""ROS 2 views of fleetctl frames: ``ros2msg`` schema texts and CDR payloads.

Tools people already use (MCAP files that ``ros2 bag`` plays, Foxglove, Lichtblick) speak
ROS 2 CDR and describe types with ``ros2msg`` schemas. This module turns the frames the
relay routes into those, generically, for every type the :class:`TypeRegistry` knows:

- :func:`schema_text`: the full ``.msg`` definition of a type with its dependencies, in
  the layout rosbag2 writes into MCAP schema records (MCAP spec, "Well-known schema
  encodings", ``ros2msg``): the type's own fields, then for each dependency a line of 80
  ``=``, a line ``MSG: pkg/Name`` and its fields. rosbags' ``Typestore.generate_msgdef``
  with ``ros_version=2`` writes exactly that (rosbags' own rosbag2 writer uses it).
- :class:`FrameTranscoder`: complete frames in, ``(metadata, type, CDR bytes)`` out.
  Fragments are reassembled (one :class:`Reassembler` per sender) and Compressed frames
  decompressed first, as every receiver does (``docs/wire.md``: reassemble, decompress,
  decode).

No I/O and no asyncio here (the wire room): callers choose the thread. A transcoder is not
thread-safe; use one per thread.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable
from typing import NamedTuple

from fleetctl.wire.codec import Codec
from fleetctl.wire.compression import COMPRESSED_TYPE, decompress
from fleetctl.wire.errors import WireError
from fleetctl.wire.fragments import FRAGMENT_TYPE, Reassembler
from fleetctl.wire.metadata import METADATA_TYPE, Metadata, normalize_type, read_root
from fleetctl.wire.registry import TypeRegistry

SCHEMA_ENCODING = "ros2msg"
"""MCAP / Foxglove schema encoding of :func:`schema_text`."""
MESSAGE_ENCODING = "cdr"
"""MCAP / Foxglove message encoding of :attr:`Transcoded.cdr`."""

# Why bounded: senders come and go; the oldest idle sender's partial messages are dropped.
_MAX_SENDERS = 1024


def schema_text(registry: TypeRegistry, type_name: str) -> str:
    """The ``ros2msg`` schema of *type_name*: its ``.msg`` text with every dependency.

    Args:
        registry: The registry that defines the type.
        type_name: Type name in any accepted form; the schema record names it
            ``pkg/msg/Name``.

    Raises:
        WireError: The type (or one it depends on) is unknown.
    """
    name = normalize_type(type_name)
    try:
        text, _md5 = registry.typestore.generate_msgdef(name, ros_version=2)
    except Exception as exc:  # rosbags raises KeyError / TypesysError for unknown types
        raise WireError(f"no ros2msg schema for {name}: {exc}") from None
    return text


def type_hash(registry: TypeRegistry, type_name: str) -> str:
    """The ROS 2 type hash (``RIHS01_<sha256>``, REP 2011) of *type_name*, as rosbag2
    stores it in a channel's ``topic_type_hash``.

    Raises:
        WireError: The type is unknown.
    """
    name = normalize_type(type_name)
    try:
        digest: str = registry.typestore.hash_rihs01(name)
    except Exception as exc:
        raise WireError(f"no type hash for {name}: {exc}") from None
    return digest


class Transcoded(NamedTuple):
    """One complete message as ROS 2 CDR.

    Attributes:
        meta: The metadata of the original (reassembled, decompressed) frame.
        type: Its ROS 2 type name (``meta.type``).
        cdr: The message serialized as CDR (little endian, with the 4-byte encapsulation
            header), as rosbag2 stores it.
    """

    meta: Metadata
    type: str
    cdr: bytes


class FrameTranscoder:
    """Frames of many senders in, CDR messages out.

    Args:
        codec: The codec whose registry knows the types.
        max_message_bytes: Largest reassembled or decompressed frame accepted, bytes.
        reassembly_timeout_s: A partial message older than this is dropped, seconds.
        max_senders: Senders whose partial messages are kept; one more forgets the
            sender used least recently.
        max_pending_bytes: Declared bytes of all senders' partial messages together;
            past it the partial messages of the senders used least recently are
            dropped. Default: four times *max_message_bytes*.
    """

    def __init__(self, codec: Codec, max_message_bytes: int, reassembly_timeout_s: float = 10.0,
                 max_senders: int = _MAX_SENDERS, max_pending_bytes: int | None = None,
                 ) -> None:
        self.codec = codec
        self.max_message_bytes = max_message_bytes
        self.max_pending_bytes = (4 * max_message_bytes if max_pending_bytes is None
                                  else max_pending_bytes)
        self.evicted_senders = 0
        self._dropped_before = 0  # drops counted by reassemblers since forgotten
        self.reassembly_timeout_s = reassembly_timeout_s
        self.max_senders = max_senders
        self._reassemblers: OrderedDict[Hashable, Reassembler] = OrderedDict()
        self._serialize = codec.registry.typestore.serialize_cdr

    def feed(self, sender: Hashable, frame: bytes, now_s: float,
             read: tuple[Metadata, int] | None = None) -> Transcoded | None:
        """Take one frame of *sender*; return the message it completes, if any.

        Args:
            sender: Who sent the frame (fragments of different senders never mix).
            frame: One frame as relayed (possibly a fragment, possibly Compressed).
            now_s: Monotonic clock, seconds (reassembly timeouts).
            read: ``read_root(frame)`` if the caller has it already (saves reading the
                metadata twice).

        Returns:
            ``None`` while a fragmented message is incomplete (or was dropped by the
            reassembler's bounds, counted in its stats).

        Raises:
            WireError: The frame, the reassembled frame or its compressed payload is
                malformed, or its type is unknown.
        """
        meta, root = read if read is not None else read_root(frame)
        if meta.type == FRAGMENT_TYPE:
            whole = self._reassemble(sender, frame, now_s)
            if whole is None:
                return None
            meta, root = read_root(whole)
        else:
            whole = frame
        if meta.type == COMPRESSED_TYPE:
            whole = decompress(whole, self.max_message_bytes, frame_codec=self.codec)
            meta, root = read_root(whole)
        if meta.type in (FRAGMENT_TYPE, COMPRESSED_TYPE, METADATA_TYPE):
            raise WireError(f"{meta.type} nested inside a frame on {meta.topic}")
        # One metadata read per frame: decode the root table found above (Codec.decode
        # would read the metadata again).
        msg = self.codec.decode_table(whole, meta.type, root)
        try:
            cdr = self._serialize(msg, meta.type)
        except Exception as exc:  # rosbags: SerdeError, or a field of the wrong shape
            raise WireError(f"cannot serialize a {meta.type} on {meta.topic} as CDR: "
                            f"{exc}") from None
        return Transcoded(meta, meta.type, bytes(cdr))

    @property
    def dropped(self) -> int:
        """Fragments and partial messages dropped so far (superseded, timed out, over a
        bound, malformed, stale; a forgotten sender's partial messages)."""
        return self._dropped_before + sum(r.stats.dropped for r in self._reassemblers.values())

    def forget(self, sender: Hashable) -> None:
        """Drop *sender*'s partial messages (it disconnected)."""
        gone = self._reassemblers.pop(sender, None)
        if gone is not None:
            self._count_gone(gone)

    def _count_gone(self, gone: Reassembler) -> None:
        self._dropped_before += gone.stats.dropped + gone.pending_messages

    def _reassemble(self, sender: Hashable, frame: bytes, now_s: float) -> bytes | None:
        reassembler = self._reassemblers.get(sender)
        if reassembler is None:
            if len(self._reassemblers) >= self.max_senders:
                self._count_gone(self._reassemblers.popitem(last=False)[1])
                self.evicted_senders += 1
            reassembler = Reassembler(self.max_message_bytes, self.reassembly_timeout_s,
                                      codec=self.codec)
            self._reassemblers[sender] = reassembler
        else:
            self._reassemblers.move_to_end(sender)
        whole = reassembler.feed(frame, now_s)
        self._bound_pending()
        return whole

    def _bound_pending(self) -> None:
        """Drop the least recently used senders' partial messages while all of them
        together declare more than ``max_pending_bytes`` (the newest sender is kept)."""
        pending = sum(r.pending_bytes for r in self._reassemblers.values())
        while pending > self.max_pending_bytes and len(self._reassemblers) > 1:
            _sender, oldest = self._reassemblers.popitem(last=False)
            pending -= oldest.pending_bytes
            self._count_gone(oldest)
            self.evicted_senders += 1
