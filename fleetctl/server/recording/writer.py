"""Frames in, rotating MCAP files out, within the disk bounds (the recorder's worker).

:class:`RecordingWriter` is synchronous and single-threaded; it runs in the recorder's
worker process (:mod:`fleetctl.server.recording.worker`), where CDR transcoding, zstd and
disk writes cannot hold the relay's GIL. Every loss is counted by reason and logged (at
most one WARNING per reason per :data:`LOG_INTERVAL_S`):

- ``too_big``: a message larger than ``max_file_bytes``;
- ``malformed``: a frame that does not reassemble, decompress or decode;
- ``write_error``: a failed write; the file is abandoned (readable up to its last flushed
  chunk) and the next message opens a new one;
- ``incomplete``: fragments of messages that never completed (superseded, timed out, over
  the reassembly bounds; counted by :class:`FrameTranscoder`).

Latched topics (a map, ``/tf_static``) are published once: the last message of each is
kept and written again at the start of every new file (log time = the file's first
message, publish time = the original), so a rotated file opened or replayed alone still
has its map and its static TF. Kept: at most :data:`MAX_LATCHED_TOPICS` topics and a
quarter of ``max_file_bytes`` (so the copies never fill a new file); a latched message
past that is recorded as usual but not repeated (one WARNING per topic). Video topics
(``CompressedVideo``) likewise: a new file starts with each one's frames since its last
keyframe (:mod:`fleetctl.server.recording.gop`, another quarter of ``max_file_bytes``), so
its camera is decodable from the file's first moment, not from the next keyframe.

Disk: before a new file starts, and at every flush tick, closed files past
``max_age_s`` or past ``max_total_bytes - max_file_bytes`` (so that a full current file
still fits) are deleted, oldest first, counted by reason and logged at INFO (the bound
doing what it was configured to do). A WARNING (at most one per
:data:`SHORT_BUDGET_LOG_INTERVAL_S`) only when ``max_total_bytes`` deletes a file last
written under :data:`MIN_HELD_S` ago: the budget is too small for the traffic recorded.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from fleetctl.server.recording import files
from fleetctl.server.recording.config import RecordingConfig
from fleetctl.server.recording.gop import VIDEO_TYPE, GopFrame, GopKeeper
from fleetctl.server.recording.mcapfile import McapFile
from fleetctl.wire.codec import Codec
from fleetctl.wire.errors import WireError
from fleetctl.wire.ros2msg import FrameTranscoder

log = logging.getLogger("fleetctl.server.recording")

LOG_INTERVAL_S = 10.0
# The byte bound deleting a file last written less than this ago (seconds) means the
# budget holds too little recording to be useful; said at most once per interval below.
MIN_HELD_S = 600.0
SHORT_BUDGET_LOG_INTERVAL_S = 3600.0
WRITER_DROP_REASONS = ("too_big", "malformed", "write_error", "incomplete")
DELETE_REASONS = ("max_total_bytes", "max_age")
MAX_LATCHED_TOPICS = 256


class _Latched(NamedTuple):
    """The last message of a latched topic, for the start of the next file."""

    type_name: str
    cdr: bytes
    publish_ns: int
    seq: int


class WriterStats:
    """Counters of a writer (JSON-ready through :meth:`snapshot`)."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self.messages = 0
        self.bytes = 0
        self.files_opened = 0
        self.dropped = dict.fromkeys(WRITER_DROP_REASONS, 0)
        self.deleted_files = dict.fromkeys(DELETE_REASONS, 0)
        self.deleted_bytes = dict.fromkeys(DELETE_REASONS, 0)
        self._clock = clock
        self.transcoder: FrameTranscoder | None = None  # counts "incomplete"
        self._logged_s: dict[str, float] = {}
        self._since_log: dict[str, int] = {}

    def drop(self, reason: str, detail: str) -> None:
        """Count one dropped message; log a WARNING unless one was logged recently."""
        self.dropped[reason] += 1
        rate_limited_warning(self._logged_s, self._since_log, reason, detail,
                             self.dropped[reason], self._clock())

    def snapshot(self) -> dict[str, Any]:
        """The counters as a JSON-ready dict."""
        dropped = dict(self.dropped)
        if self.transcoder is not None:
            dropped["incomplete"] = self.transcoder.dropped
        return {"messages": self.messages, "bytes": self.bytes,
                "files_opened": self.files_opened, "dropped": dropped,
                "deleted_files": dict(self.deleted_files),
                "deleted_bytes": dict(self.deleted_bytes)}


def rate_limited_warning(logged_s: dict[str, float], since: dict[str, int], reason: str,
                         detail: str, total: int, now_s: float) -> None:
    """Log "recording dropped ..." for *reason* at most once per :data:`LOG_INTERVAL_S`,
    with the count since the last line."""
    since[reason] = since.get(reason, 0) + 1
    if now_s - logged_s.get(reason, -LOG_INTERVAL_S) < LOG_INTERVAL_S:
        return
    n, since[reason] = since[reason], 0
    logged_s[reason] = now_s
    log.warning("recording dropped %d message(s) (%s: %s); %d dropped for %s so far",
                n, reason, detail, total, reason)


class RecordingWriter:
    """Writes frames into the recording directory.

    Args:
        config: The ``recording:`` section.
        codec: Decodes the frames; its registry gives the schemas.
        max_message_bytes: Largest reassembled or decompressed frame, bytes.
        clock: Monotonic clock, seconds.
        wall_clock_s: Wall clock, seconds since the epoch (file names, the age bound).
    """

    def __init__(self, config: RecordingConfig, codec: Codec, max_message_bytes: int,
                 clock: Callable[[], float] = time.monotonic,
                 wall_clock_s: Callable[[], float] = time.time) -> None:
        self.config = config
        self.codec = codec
        self.stats = WriterStats(clock)
        self._clock = clock
        self._wall_s = wall_clock_s
        self._transcoder = FrameTranscoder(codec, max_message_bytes)
        self.stats.transcoder = self._transcoder
        self._file: McapFile | None = None
        self._file_started_s = 0.0
        self._last_flush_s = clock()
        self.disk_bytes = 0  # .mcap bytes in the directory, as of the last bounds check
        self._latched: dict[str, _Latched] = {}
        self._not_kept: set[str] = set()  # latched topics warned about (bounded as above)
        self._budget_warned_s: float | None = None  # monotonic; None: not yet
        self._gops = GopKeeper(config.max_file_bytes // 4,
                               codec.registry.typestore.deserialize_cdr)

    @property
    def current_path(self) -> Path | None:
        """The file being written, if any."""
        return self._file.path if self._file is not None else None

    @property
    def current_topics(self) -> list[str]:
        """The topics in the file being written, sorted."""
        return sorted(self._file.topics) if self._file is not None else []

    def start(self) -> None:
        """Create the directory and apply the disk bounds.

        Raises:
            OSError: The directory cannot be created.
        """
        self.config.directory.mkdir(parents=True, exist_ok=True)
        self.enforce_bounds()

    def record(self, sender: int, frame: bytes, wall_ns: int, mono_s: float) -> None:
        """Write the message *frame* completes (fragments are held until then).

        Args:
            sender: The relay's connection id of the sender.
            frame: The frame as relayed.
            wall_ns: Wall clock at receipt (log time of a frame without publish time).
            mono_s: Monotonic clock at receipt, seconds (reassembly timeouts).
        """
        try:
            out = self._transcoder.feed(sender, frame, mono_s)
        except WireError as exc:
            self.stats.drop("malformed", str(exc))
            return
        if out is None:
            return
        meta, size = out.meta, len(out.cdr)
        if size > self.config.max_file_bytes:
            self.stats.drop("too_big", f"{size} bytes on {meta.topic}")
            return
        time_ns = meta.publish_time_ns or wall_ns
        keyframe = self._gops.keyframe(out.type, out.cdr)
        try:
            current = self._writable(size, meta.topic, time_ns, keyframe)
            current.write(meta.topic, out.type, out.cdr, time_ns, meta.seq, meta.latched)
        except (OSError, WireError) as exc:
            self.stats.drop("write_error", f"{self.current_path}: {exc}")
            self._abandon()
            return
        self.stats.messages += 1
        self.stats.bytes += size
        if meta.latched:
            self._keep_latched(meta.topic, _Latched(out.type, out.cdr, time_ns, meta.seq))
        if keyframe is not None:
            self._gops.add(meta.topic, GopFrame(out.cdr, time_ns, meta.seq), keyframe)

    def _keep_latched(self, topic: str, message: _Latched) -> None:
        kept = {t: m for t, m in self._latched.items() if t != topic}
        held = sum(len(m.cdr) for m in kept.values()) + len(message.cdr)
        if len(kept) < MAX_LATCHED_TOPICS and held <= self.config.max_file_bytes // 4:
            self._latched = {**kept, topic: message}
            return
        self._latched = kept
        if topic not in self._not_kept and len(self._not_kept) < MAX_LATCHED_TOPICS:
            self._not_kept.add(topic)
            log.warning("recording: latched %s (%d bytes) is not repeated in new files: "
                        "over the bound of %d topics or %d bytes", topic, len(message.cdr),
                        MAX_LATCHED_TOPICS, self.config.max_file_bytes // 4)

    def _write_latched(self, into: McapFile, except_topic: str, time_ns: int) -> None:
        for topic, m in self._latched.items():
            if topic != except_topic:  # its new message comes next
                into.write(topic, m.type_name, m.cdr, time_ns, m.seq, True,
                           publish_time_ns=m.publish_ns)

    def tick(self) -> None:
        """Flush the current file, rotate it when old, apply the bounds; each at most
        once per ``flush_interval_s``."""
        now = self._clock()
        if now - self._last_flush_s < self.config.flush_interval_s:
            return
        self._last_flush_s = now
        if self._file is not None:
            try:
                self._file.flush()
            except OSError as exc:
                self.stats.drop("write_error", f"{self.current_path}: {exc}")
                self._abandon()
        if self._file is not None and now - self._file_started_s >= self.config.rotate_after_s:
            self.close()
        self.enforce_bounds()

    def close(self) -> None:
        """Close the current file (summary and footer), if any."""
        current, self._file = self._file, None
        if current is None:
            return
        try:
            current.close()
        except OSError as exc:
            self.stats.drop("write_error", f"{current.path}: closing: {exc}")
        log.info("recording file %s closed (%d messages)", current.path, current.messages)

    def enforce_bounds(self) -> None:
        """Delete closed files past ``max_age_s`` or the byte bound (counted, logged)."""
        cfg = self.config
        try:
            deleted = files.enforce_bounds(cfg.directory, self.current_path,
                                           cfg.max_total_bytes - cfg.max_file_bytes,
                                           cfg.max_age_s, self._wall_s())
        except OSError as exc:
            log.warning("recording: cannot apply the disk bounds in %s: %s",
                        cfg.directory, exc)
            return
        with contextlib.suppress(OSError):
            self.disk_bytes = sum(f.size_bytes for f in files.scan(cfg.directory))
        for f, reason in deleted:
            self.stats.deleted_files[reason] += 1
            self.stats.deleted_bytes[reason] += f.size_bytes
            # The configured bound doing its job: INFO, not WARNING (was a WARNING every
            # ~75 s with a 64 MiB budget, which trains operators to ignore warnings).
            log.info("recording: deleted %s (%d bytes) to hold %s", f.name, f.size_bytes,
                     reason)
            if reason == "max_total_bytes":
                self._warn_if_budget_short(f)

    def _warn_if_budget_short(self, deleted: files.RecordingFile) -> None:
        """One WARNING per :data:`SHORT_BUDGET_LOG_INTERVAL_S` when the byte bound deleted
        a file last written less than :data:`MIN_HELD_S` ago: the directory holds only
        minutes of recording, too little to fetch a run after the fact."""
        held_s = self._wall_s() - deleted.modified_s
        now = self._clock()
        if held_s >= MIN_HELD_S or (self._budget_warned_s is not None and
                                    now - self._budget_warned_s < SHORT_BUDGET_LOG_INTERVAL_S):
            return
        self._budget_warned_s = now
        log.warning("recording: max_total_bytes (%d bytes) holds only ~%.0f s of recording "
                    "(deleted %s, last written %.0f s ago); raise recording.max_total_bytes "
                    "in server.yaml or record fewer topics (recording.rules)",
                    self.config.max_total_bytes, max(held_s, 0.0), deleted.name,
                    max(held_s, 0.0))

    def _writable(self, nbytes: int, topic: str, time_ns: int,
                  keyframe: bool | None = None) -> McapFile:
        """The file to write *nbytes* more into (a message on *topic* at *time_ns*; a
        video keyframe or delta frame, or ``None``): the current one, or a new one, which
        starts with the latched topics' last messages and the video topics' frames since
        their last keyframes, when the current would pass ``max_file_bytes`` or is older
        than the rotation period."""
        current = self._file
        if current is not None and current.messages and (
                current.size_bytes + nbytes > self.config.max_file_bytes
                or self._clock() - self._file_started_s >= self.config.rotate_after_s):
            self.close()
            current = None
        if current is None:
            path = files.new_path(self.config.directory, self._wall_s(),
                                  self.config.file_label)
            current = McapFile(path, self.codec.registry, self.config.chunk_bytes)
            self._file = current
            self._file_started_s = self._last_flush_s = self._clock()
            self.stats.files_opened += 1
            log.info("recording into %s", path)
            self.enforce_bounds()
            self._write_latched(current, topic, time_ns)
            # A keyframe opening the file makes its own topic's group useless.
            for video, frame in self._gops.groups(skip=topic if keyframe else None):
                current.write(video, VIDEO_TYPE, frame.cdr, time_ns, frame.seq, False,
                              publish_time_ns=frame.publish_ns)
        return current

    def _abandon(self) -> None:
        current, self._file = self._file, None
        if current is not None:
            current.abandon()
