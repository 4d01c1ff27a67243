"""The recorder's worker process: ``python -m fleetctl.server.recording.worker CONFIG``.

Reads frames from stdin, writes MCAP files (:class:`RecordingWriter`), and reports its
counters on stdout as JSON lines. A process, not a thread: transcoding to CDR and writing
MCAP cost ~6 us of Python per message, which in a thread would hold the relay's GIL
(docs/server.md, "Recording", has the measurements).

Protocol (one direction each, no replies):

- stdin: records ``<u32 sender><i64 wall clock ns><u32 length><frame>`` (little endian),
  as the relay accepted them, in order; EOF means stop: the current file is closed.
- stdout: ``{"stats": {...}, "current": path | null, "topics": [...], "disk_bytes": n}``
  lines (the current file's topics; the directory's bytes at the last bounds check),
  after changes (at most every :data:`STATS_INTERVAL_S`) and a
  last one before exiting.
- stderr: log lines.

The worker ignores SIGINT, SIGTERM and SIGHUP: it stops at EOF, which also comes when the
server dies, so the current file is always closed with its summary.

CONFIG is a JSON object: :func:`config_to_json` of the recording config plus
``max_message_bytes`` and ``msg_types_file`` (the fleet's own message types,
:mod:`fleetctl.server.recording.typesfile`; ``null``: none).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import signal
import struct
import sys
import time
from pathlib import Path
from typing import Any, BinaryIO

from fleetctl.server.msgtypes import codec_for
from fleetctl.server.recording.config import RecordingConfig
from fleetctl.server.recording.typesfile import read_types_file
from fleetctl.server.recording.writer import RecordingWriter
from fleetctl.wire.codec import Codec, default_codec
from fleetctl.wire.errors import WireError

log = logging.getLogger("fleetctl.server.recording")

HEADER = struct.Struct("<IqI")
"""Record header on stdin: sender id, wall clock ns at receipt, frame length."""
STATS_INTERVAL_S = 0.05
READ_BYTES = 1 << 20

_NUMBERS = ("max_file_bytes", "max_file_duration_s", "max_total_bytes", "max_age_s",
            "queue_bytes", "chunk_bytes", "flush_interval_s", "worker_priority",
            "file_label")


def config_to_json(config: RecordingConfig, max_message_bytes: int,
                   msg_types_file: Path | None = None) -> str:
    """The worker's command-line argument for *config* (rules stay in the relay)."""
    data: dict[str, Any] = {name: getattr(config, name) for name in _NUMBERS}
    data["directory"] = str(config.directory)
    data["max_message_bytes"] = max_message_bytes
    data["msg_types_file"] = None if msg_types_file is None else str(msg_types_file)
    return json.dumps(data)


def config_from_json(text: str) -> tuple[RecordingConfig, int, Path | None]:
    """Inverse of :func:`config_to_json`: the config (without rules), the largest
    message and the message types' file."""
    data = json.loads(text)
    max_message_bytes = int(data.pop("max_message_bytes"))
    directory = Path(data.pop("directory"))
    types_file = data.pop("msg_types_file", None)
    return (RecordingConfig(directory, (), **data), max_message_bytes,
            None if types_file is None else Path(types_file))


def worker_codec(types_file: Path | None) -> Codec:
    """The default codec plus the fleet's own types of *types_file*. One that cannot be
    read leaves the default types (the relay checked them at start, so this is a file
    removed behind its back): logged, and the own types' messages are dropped as
    ``malformed``, as before there were any."""
    if types_file is None:
        return default_codec()
    try:
        return codec_for(read_types_file(types_file))
    except (OSError, ValueError, WireError) as exc:
        log.error("recording without the fleet's own message types: %s", exc)
        return default_codec()


def serve(fd_in: int, out: BinaryIO, writer: RecordingWriter) -> None:
    """Record what arrives on *fd_in* until EOF; report counters on *out*."""
    buf = bytearray()
    reported: dict[str, Any] | None = None
    reported_s = 0.0
    tick_s = min(writer.config.flush_interval_s, STATS_INTERVAL_S)
    eof = False
    while not eof:
        ready, _, _ = select.select([fd_in], [], [], tick_s)
        if ready:
            data = os.read(fd_in, READ_BYTES)
            eof = not data
            buf += data
            del buf[:_records(buf, writer)]
        writer.tick()
        now = time.monotonic()
        if now - reported_s >= STATS_INTERVAL_S:
            line = _report_line(writer)
            if line != reported:
                _send(out, line)
                reported, reported_s = line, now
    writer.close()
    _send(out, _report_line(writer))


def _records(buf: bytearray, writer: RecordingWriter) -> int:
    """Record every complete record at the start of *buf*; return the bytes consumed."""
    pos, n, size = 0, len(buf), HEADER.size
    while n - pos >= size:
        sender, wall_ns, length = HEADER.unpack_from(buf, pos)
        end = pos + size + length
        if end > n:
            break
        writer.record(sender, bytes(buf[pos + size:end]), wall_ns, time.monotonic())
        pos = end
    return pos


def _report_line(writer: RecordingWriter) -> dict[str, Any]:
    current = writer.current_path
    return {"stats": writer.stats.snapshot(),
            "current": None if current is None else str(current),
            "topics": writer.current_topics, "disk_bytes": writer.disk_bytes}


def _send(out: BinaryIO, line: dict[str, Any]) -> None:
    out.write(json.dumps(line).encode() + b"\n")
    out.flush()


def _lower_priority(priority: str) -> None:
    """``idle``: Linux ``SCHED_IDLE`` (runs only on CPU time nothing else wants), else the
    lowest niceness; ``normal``: as the relay."""
    if priority != "idle":
        return
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        with contextlib.suppress(OSError):
            os.nice(19)


def main(argv: list[str]) -> int:
    """Run the worker; *argv* is ``[CONFIG]``."""
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s %(message)s")
    config, max_message_bytes, types_file = config_from_json(argv[0])
    _lower_priority(config.worker_priority)
    # The server ends the worker by closing the pipe (EOF: the file is closed properly);
    # a Ctrl-C or a service manager's SIGTERM to the whole group must not cut it short.
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    writer = RecordingWriter(config, worker_codec(types_file), max_message_bytes)
    writer.start()
    try:
        serve(sys.stdin.fileno(), sys.stdout.buffer, writer)
    except BrokenPipeError:  # the server went away: close the file all the same
        writer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
