"""The recorder: relayed frames in (event loop), MCAP files out (a worker process).

The relay core calls :meth:`Recorder.offer` for every accepted frame. On the event loop
it costs one dict lookup when no rule matches (the decision is cached per topic and
identity set) and, when one does, a header and the frame appended to a list. In batches
(:data:`FLUSH_DELAY_S`, :data:`FLUSH_BYTES`) the list is joined and written,
non-blocking, to a pipe to the worker process (:mod:`fleetctl.server.recording.worker`),
which does everything else (reassembly, decompression, decoding, CDR, MCAP, zstd, disk)
outside the relay's GIL.

Why no thread: a feeder thread in the relay's process measured 0.75x the relay's
throughput and a p99 of 13-17 ms (against 3 ms) at half load: every frame it touched
in Python cost the event loop a GIL hand-off, and a batch it copied held the GIL for
up to the interpreter's 5 ms switch interval (docs/server.md, "Recording").

Bounds, each counted and logged (at most one WARNING per reason per ten seconds):

- ``queue_bytes``: frames the pipe has not taken yet; a frame that does not fit is
  dropped (``queue_full``): a slow disk or a busy worker costs recorded data, never
  relay throughput or memory (the pipe's own buffer, 1 MiB where Linux allows it, adds
  to it);
- the worker counts ``too_big``, ``malformed`` and ``write_error`` and deletes files past
  the disk bounds (:mod:`fleetctl.server.recording.writer`);
- a worker that dies is logged and restarted (:data:`RESTART_MIN_S` ...
  :data:`RESTART_MAX_S`); frames meanwhile are dropped (``worker_exited``), and the
  counters carry on from the dead worker's. The new worker's file starts with the
  relay's latched messages (:attr:`Recorder.latched_source`), as every rotated file does:
  a robot sends its map once, so without them the new file would have none.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import json
import logging
import os
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from fleetctl.server.msgtypes import MsgTypes
from fleetctl.server.permissions import Permissions
from fleetctl.server.recording.config import RecordingConfig
from fleetctl.server.recording.rules import RecordingRules
from fleetctl.server.recording.typesfile import write_types_file
from fleetctl.server.recording.worker import HEADER, config_to_json
from fleetctl.server.recording.writer import (
    DELETE_REASONS,
    WRITER_DROP_REASONS,
    rate_limited_warning,
)

log = logging.getLogger("fleetctl.server.recording")

RECORDER_DROP_REASONS = ("queue_full", "worker_exited")
DROP_REASONS = (*RECORDER_DROP_REASONS, *WRITER_DROP_REASONS)

# The connection id of latched messages handed to a restarted worker (the relay's are
# counted from 1 and never get this far): their fragments reassemble apart from a live
# sender's.
LATCHED_SENDER = 0xFFFFFFFF
RESTART_MIN_S = 1.0
RESTART_MAX_S = 60.0
"""A dead worker is restarted after 1 s, then 2, 4... up to 60 s while it keeps dying
(back to 1 s once one ran for a minute)."""

FLUSH_DELAY_S = 0.002
FLUSH_BYTES = 256 * 1024
"""New frames are written to the pipe 2 ms after the first of them, or at once when
256 KiB are waiting: one write (and one wake-up of the worker) per batch, not per frame
or per loop iteration."""

PIPE_BYTES = 1 << 20
"""Pipe buffer asked for (``F_SETPIPE_SZ``): fewer wake-ups of the loop's writer."""
_F_SETPIPE_SZ = getattr(fcntl, "F_SETPIPE_SZ", 1031)


class Recorder:
    """Records frames matching the config's rules into rotating MCAP files.

    Args:
        config: The ``recording:`` section.
        max_message_bytes: Largest reassembled or decompressed frame, bytes (the relay's
            ``max_frame_bytes``).
        wall_clock_ns: Wall clock (log time of frames without a publish time).
        clock: Monotonic clock, seconds (log rate limits).
        msg_types: The fleet's own message types (``server.yaml`` ``msg_types``), which
            the worker decodes with the default ones.
    """

    def __init__(self, config: RecordingConfig, max_message_bytes: int = 16 * 1024 * 1024,
                 wall_clock_ns: Callable[[], int] = time.time_ns,
                 clock: Callable[[], float] = time.monotonic,
                 msg_types: MsgTypes = ()) -> None:
        self.config = config
        self.max_message_bytes = max_message_bytes
        self.msg_types = msg_types
        self._types_file: Path | None = None  # msg_types for the worker (typesfile)
        self.rules = RecordingRules(config.rules)
        self._wall_ns = wall_clock_ns
        self._clock = clock
        self._parts: list[bytes] = []  # headers and frames of the next batch
        self._chunks: deque[memoryview] = deque()  # joined, not yet taken by the pipe
        self._queued_bytes = 0
        self._flush_handle: asyncio.TimerHandle | None = None
        self._flush_now = False  # the armed flush runs without the delay
        self._parts_bytes = 0
        self._writer_added = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._fd = -1
        self._closed = False  # detach() ran: the loop no longer writes
        self._dead = False
        self._lock = threading.Lock()  # _dropped, read by /metrics and the report thread
        self._dropped = dict.fromkeys(RECORDER_DROP_REASONS, 0)
        self._logged_s: dict[str, float] = {}
        self._since_log: dict[str, int] = {}
        self._worker_stats: dict[str, Any] = {}  # the running worker's last report
        self._base_stats: dict[str, Any] = {}  # what earlier workers counted
        self._restart_delay_s = RESTART_MIN_S / 2
        self._spawned_s = 0.0
        self._queued_frames = 0
        self.current_path: str | None = None
        self.current_topics: list[str] = []
        self.disk_bytes = 0  # as the worker last reported (no directory scan on the loop)
        self._process: subprocess.Popen[bytes] | None = None
        self._reports: threading.Thread | None = None
        # The relay's latched messages, ``(sender identities, topic, frames)``: given to
        # a restarted worker (set by the relay; ``None``: none).
        self.latched_source: Callable[[], list[tuple[tuple[str, ...], str,
                                                     list[bytes]]]] | None = None

    # -- event loop side ------------------------------------------------------------

    def offer(self, sender: int, perms: Permissions, topic: str, frame: bytes) -> None:
        """Queue *frame* (accepted on *topic* from connection *sender* with *perms*) if
        a rule says to record it. Never blocks; a full queue drops the frame (counted).
        Call on the event loop's thread."""
        if self.rules.matches(topic, perms):
            self._queue(sender, frame)

    def _queue(self, sender: int, frame: bytes) -> None:
        n = HEADER.size + len(frame)
        if self._dead or self._closed or self._queued_bytes + n > self.config.queue_bytes:
            self._drop("worker_exited" if self._dead or self._closed else "queue_full")
            return
        self._parts += (HEADER.pack(sender & 0xFFFFFFFF, self._wall_ns(), len(frame)), frame)
        self._queued_bytes += n
        self._queued_frames += 1
        self._parts_bytes += n
        # At most two timer operations per batch: a socket read can hand the relay
        # thousands of frames before the loop runs a timer, and re-arming the flush for
        # each of them once the batch was full cost a quarter of the relay's time.
        handle = self._flush_handle
        if handle is None:
            if self._loop is not None:
                self._arm_flush(self._parts_bytes >= FLUSH_BYTES)
        elif self._parts_bytes >= FLUSH_BYTES and not self._flush_now:
            handle.cancel()  # enough for one write: now, not after the delay
            self._arm_flush(True)

    def _arm_flush(self, now: bool) -> None:
        assert self._loop is not None
        self._flush_now = now
        self._flush_handle = self._loop.call_at(
            self._loop.time() + (0.0 if now else FLUSH_DELAY_S), self._flush)

    @property
    def queued_bytes(self) -> int:
        """Bytes offered that the pipe has not taken yet."""
        return self._queued_bytes

    def snapshot(self) -> dict[str, Any]:
        """The counters, JSON-ready: ``messages``, ``bytes``, ``files_opened``,
        ``dropped``/``deleted_files``/``deleted_bytes`` by reason (the worker's as of its
        last report, a few tens of ms old)."""
        with self._lock:
            worker = _add_stats(self._base_stats, self._worker_stats)
            dropped = {**dict.fromkeys(DROP_REASONS, 0), **worker.get("dropped", {}),
                       **self._dropped}
        return {"messages": worker.get("messages", 0), "bytes": worker.get("bytes", 0),
                "files_opened": worker.get("files_opened", 0), "dropped": dropped,
                "deleted_files": {**dict.fromkeys(DELETE_REASONS, 0),
                                  **worker.get("deleted_files", {})},
                "deleted_bytes": {**dict.fromkeys(DELETE_REASONS, 0),
                                  **worker.get("deleted_bytes", {})}}

    @property
    def worker_pid(self) -> int | None:
        """Process id of the worker (e.g. to pin it to a core), or ``None``."""
        return self._process.pid if self._process is not None else None

    def start(self) -> None:
        """Create the directory, start the worker process. Call on the event loop.

        Raises:
            OSError: The directory cannot be created or the worker cannot start.
        """
        self.config.directory.mkdir(parents=True, exist_ok=True)
        self._loop = asyncio.get_running_loop()
        if self.msg_types and self._types_file is None:
            self._types_file = write_types_file(self.msg_types)
        self._spawn()

    def _spawn(self) -> None:
        self._process = subprocess.Popen(
            [sys.executable, "-m", "fleetctl.server.recording.worker",
             config_to_json(self.config, self.max_message_bytes, self._types_file)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0, close_fds=True)
        assert self._process.stdin is not None and self._process.stdout is not None
        self._fd = self._process.stdin.fileno()
        with contextlib.suppress(OSError):  # not Linux, or over /proc/sys/fs/pipe-max-size
            fcntl.fcntl(self._fd, _F_SETPIPE_SZ, PIPE_BYTES)
        os.set_blocking(self._fd, False)
        with self._lock:
            self._dead = False
        self._reports = threading.Thread(target=self._read_reports,
                                         args=(self._process, self._process.stdout),
                                         name="fleetctl-recorder-reports", daemon=True)
        self._reports.start()
        self._spawned_s = self._clock()
        log.info("recording %d rule(s) into %s (worker pid %d)", len(self.config.rules),
                 self.config.directory, self._process.pid)

    def detach(self) -> None:
        """Stop writing from the event loop (call on it before :meth:`stop`); frames
        offered later are dropped."""
        self._closed = True
        if self._flush_handle is not None:
            self._flush_handle.cancel()
            self._flush_handle = None
        if self._writer_added and self._loop is not None:
            self._loop.remove_writer(self._fd)
            self._writer_added = False
        self._join()

    def stop(self, timeout_s: float = 30.0) -> None:
        """Hand the rest to the worker, let it close its file (summary and footer), wait
        for it. Blocking: call :meth:`detach` on the loop first, then this in a worker
        thread."""
        self._closed = True
        process = self._process
        if process is None:
            self._remove_types_file()
            return
        self._join()
        if not self._dead and process.stdin is not None:
            try:
                os.set_blocking(self._fd, True)
                while self._chunks:
                    _write_all(self._fd, self._chunks.popleft())
            except OSError as exc:
                self._worker_gone(f"writing to it failed: {exc}", process)
        self._chunks.clear()
        self._queued_bytes = 0
        if process.stdin is not None:
            with contextlib.suppress(OSError):
                process.stdin.close()  # EOF: the worker closes its file and exits
        try:
            process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            log.error("recording worker %d did not stop in %.0f s: killed", process.pid,
                      timeout_s)
            process.kill()
            process.wait()
        if self._reports is not None:
            self._reports.join(timeout_s)
        self._process = None
        self._remove_types_file()

    def _remove_types_file(self) -> None:
        if self._types_file is not None:
            self._types_file.unlink(missing_ok=True)
            self._types_file = None

    def metric_families(self) -> list[tuple[str, str, str, str, dict[str, float]]]:
        """``(name, type, help, label, {label_value: value})`` for ``/metrics``."""
        snap = self.snapshot()
        disk = float(self.disk_bytes)
        return [
            ("fleetctl_recording_messages_total", "counter", "Messages written to MCAP.",
             "", {"": float(snap["messages"])}),
            ("fleetctl_recording_bytes_total", "counter",
             "CDR payload bytes written to MCAP.", "", {"": float(snap["bytes"])}),
            ("fleetctl_recording_dropped_total", "counter",
             "Frames or messages the recorder dropped, by reason (queue_full, "
             "worker_exited, too_big, malformed, write_error, incomplete).", "reason",
             {k: float(v) for k, v in snap["dropped"].items()}),
            ("fleetctl_recording_deleted_files_total", "counter",
             "Recording files deleted by a disk bound (max_total_bytes, max_age).",
             "reason", {k: float(v) for k, v in snap["deleted_files"].items()}),
            ("fleetctl_recording_deleted_bytes_total", "counter",
             "Bytes of recording files deleted by a disk bound.", "reason",
             {k: float(v) for k, v in snap["deleted_bytes"].items()}),
            ("fleetctl_recording_queue_bytes", "gauge",
             "Bytes of frames the pipe to the recording worker has not taken yet.", "",
             {"": float(self._queued_bytes)}),
            ("fleetctl_recording_disk_bytes", "gauge",
             "Bytes of .mcap files in the recording directory (as of the worker's last "
             "bounds check, at most flush_interval_s old).", "", {"": disk}),
        ]

    # -- writing to the pipe (event loop) ---------------------------------------------

    def _join(self) -> None:
        if self._parts:
            self._chunks.append(memoryview(b"".join(self._parts)))
            self._parts = []
            self._parts_bytes = 0

    def _flush(self) -> None:
        """:data:`FLUSH_DELAY_S` after the first new frame, or once :data:`FLUSH_BYTES`
        arrived: join the frames, write what the pipe takes."""
        self._flush_handle = None
        if self._closed:
            return
        self._join()
        if not self._writer_added:
            self._write()

    def _write(self) -> None:
        chunks = self._chunks
        try:
            while chunks:
                n = os.write(self._fd, chunks[0])
                self._queued_bytes -= n
                if n == len(chunks[0]):
                    chunks.popleft()
                else:
                    chunks[0] = chunks[0][n:]
        except BlockingIOError:
            pass  # the pipe is full: go on when it takes more
        except OSError as exc:
            self._worker_gone(f"writing to it failed: {exc}", self._process)
        if not chunks:
            self._queued_frames = 0
        self._watch_writable(bool(chunks) and not self._dead)

    def _watch_writable(self, wanted: bool) -> None:
        if wanted == self._writer_added or self._loop is None:
            return
        if wanted:
            self._loop.add_writer(self._fd, self._write)
        else:
            self._loop.remove_writer(self._fd)
        self._writer_added = wanted

    # -- other threads --------------------------------------------------------------

    def _drop(self, reason: str) -> None:
        with self._lock:
            self._dropped[reason] += 1
            total = self._dropped[reason]
        rate_limited_warning(self._logged_s, self._since_log, reason,
                             f"{self.config.queue_bytes} bytes queued for the worker"
                             if reason == "queue_full" else "the worker process is gone",
                             total, self._clock())

    def _read_reports(self, process: subprocess.Popen[bytes], pipe: IO[bytes]) -> None:
        for line in pipe:
            try:
                report = json.loads(line)
                with self._lock:
                    if process is not self._process or self._dead:
                        continue  # a report of a worker already counted as gone
                    self._worker_stats = report["stats"]
                    self.current_path = report["current"]
                    self.current_topics = report.get("topics", [])
                    self.disk_bytes = int(report.get("disk_bytes", 0))
            except (ValueError, KeyError, TypeError):
                log.warning("recording worker: unreadable report %r", line[:200])
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(5)  # its output ended: it is exiting (and must not stay a zombie)
        if not self._closed:
            self._worker_gone("its output ended", process)

    def _worker_gone(self, why: str, process: subprocess.Popen[bytes] | None) -> None:
        """Worker *process* died (any thread): count what it had, restart it later."""
        with self._lock:
            if self._dead or process is not self._process:
                return
            self._dead = True
            self._base_stats = _add_stats(self._base_stats, self._worker_stats)
            self._worker_stats = {}
        code = self._process.poll() if self._process is not None else None
        up_s = self._clock() - self._spawned_s
        self._restart_delay_s = (RESTART_MIN_S if up_s > RESTART_MAX_S
                                 else min(RESTART_MAX_S, self._restart_delay_s * 2))
        log.error("recording worker exited (%s; exit code %s): frames are dropped until it "
                  "restarts in %.0f s", why, code, self._restart_delay_s)
        if self._loop is not None and not self._closed:
            with contextlib.suppress(RuntimeError):  # the loop is closed: nothing to do
                self._loop.call_soon_threadsafe(self._schedule_restart)

    def _schedule_restart(self) -> None:
        """On the loop: forget what the dead worker did not take, restart it later."""
        self._watch_writable(False)
        if self._process is not None and self._process.stdin is not None:
            with contextlib.suppress(OSError):
                self._process.stdin.close()
        lost = self._queued_frames
        self._parts, self._queued_bytes, self._queued_frames = [], 0, 0
        self._parts_bytes = 0
        self._chunks.clear()
        if lost:
            with self._lock:
                self._dropped["worker_exited"] += lost
        assert self._loop is not None
        self._loop.call_later(self._restart_delay_s, self._restart)

    def _restart(self) -> None:
        if self._closed:
            return
        try:
            self._spawn()
        except OSError as exc:
            self._process = None
            with self._lock:
                self._dead = False  # so that _worker_gone counts and schedules again
            self._worker_gone(f"cannot start it: {exc}", None)
            return
        self._queue_latched()

    def _queue_latched(self) -> None:
        """Queue the relay's latched messages a rule records, for the new worker's file."""
        if self.latched_source is None:
            return
        for names, topic, frames in self.latched_source():
            if self.rules.matches_names(topic, frozenset(names)):
                for frame in frames:
                    self._queue(LATCHED_SENDER, frame)


def _add_stats(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Counters of two workers added (numbers, and dicts of numbers by reason)."""
    out: dict[str, Any] = dict(a)
    for key, value in b.items():
        if isinstance(value, dict):
            merged = dict(out.get(key, {}))
            for k, v in value.items():
                merged[k] = merged.get(k, 0) + v
            out[key] = merged
        else:
            out[key] = out.get(key, 0) + value
    return out


def _write_all(fd: int, data: memoryview) -> None:
    while data:
        data = data[os.write(fd, data):]
