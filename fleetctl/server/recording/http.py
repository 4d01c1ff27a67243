"""``GET /recordings`` and ``GET /recordings/<name>`` on the relay port.

Who may see what (docs/server.md, "Recording"): the same callers as ``/metrics`` (a
loopback caller without identity, or any identity; docs/security.md), and of the files
only those whose every topic the caller's identities may receive: a recording is the
topics' data, so it follows the receive rules. The operator on the server host sees all.

``/recordings`` answers ``{"recordings": [{name, bytes, modified_s, complete, topics}]}``.
``/recordings/<name>`` answers the file's bytes, at most :data:`MAX_RANGE_BYTES` per
response: ask for more with ``Range: bytes=<start>-`` (206 with ``Content-Range``; the
total is the size when read, which grows while the file is written). File reads run in
the default executor, never on the event loop.
"""

from __future__ import annotations

import asyncio
import http
import json
import re
from collections import OrderedDict
from pathlib import Path

from websockets.datastructures import Headers
from websockets.http11 import Response

from fleetctl.errors import FleetError
from fleetctl.server.permissions import Permissions
from fleetctl.server.recording import files
from fleetctl.server.recording.recorder import Recorder

MAX_RANGE_BYTES = 4 * 1024 * 1024
RECORDINGS_PATH = "/recordings"
# At most 18 digits: a file offset fits, and int() of a longer header (it may be 8 KiB)
# would raise ValueError past 4300 digits, a 500 with a traceback line per request.
_RANGE = re.compile(r"bytes=(\d{1,18})-(\d{0,18})")
_MAX_CACHED = 4096


class RecordingsEndpoint:
    """Answers the ``/recordings`` requests of one server.

    Args:
        recorder: The server's recorder (its directory, the file being written and that
            file's topics).
    """

    def __init__(self, recorder: Recorder) -> None:
        self.recorder = recorder
        self.directory = recorder.config.directory
        # Topics of files that no longer change, by (name, size, mtime).
        self._topics: OrderedDict[tuple[str, int, float], list[str]] = OrderedDict()

    async def respond(self, path: str, headers: Headers, perms: Permissions | None,
                      ) -> Response:
        """The answer to ``GET path``; *perms* ``None`` is the operator (sees all)."""
        loop = asyncio.get_running_loop()
        if path in (RECORDINGS_PATH, RECORDINGS_PATH + "/"):
            listing = await loop.run_in_executor(None, self._list, perms)
            body = json.dumps({"recordings": listing}).encode()
            return _response(http.HTTPStatus.OK, body, "application/json")
        name = path[len(RECORDINGS_PATH) + 1:]
        if "/" in name or not name.endswith(files.SUFFIX) or name.startswith("."):
            return _text(http.HTTPStatus.NOT_FOUND, f"no recording {name!r}\n")
        match = _RANGE.fullmatch(headers.get("Range", "bytes=0-").strip())
        if match is None:
            return _text(http.HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE,
                         "only Range: bytes=<start>-[<end>] is supported\n")
        start = int(match.group(1))
        end = int(match.group(2)) + 1 if match.group(2) else start + MAX_RANGE_BYTES
        if end <= start:  # "bytes=5-2": no bytes to send (a negative read was a 500)
            return _text(http.HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE,
                         f"the range {match.group(0)} ends before it starts\n")
        return await loop.run_in_executor(None, self._read, name, perms, start,
                                          min(end, start + MAX_RANGE_BYTES))

    def _list(self, perms: Permissions | None) -> list[dict[str, object]]:
        out: list[dict[str, object]] = []
        for f in files.scan(self.directory):
            topics = self._file_topics(f)
            if topics is None or not _may_receive(perms, topics):
                continue
            out.append({"name": f.name, "bytes": f.size_bytes, "modified_s": f.modified_s,
                        "complete": f.path != self._current(), "topics": topics})
        return out

    def _read(self, name: str, perms: Permissions | None, start: int, end: int) -> Response:
        found = [f for f in files.scan(self.directory) if f.name == name]
        topics = self._file_topics(found[0]) if found else None
        if topics is None or not _may_receive(perms, topics):
            # The same answer for "missing" and "not yours": names are not disclosed.
            return _text(http.HTTPStatus.NOT_FOUND, f"no recording {name!r}\n")
        with found[0].path.open("rb") as stream:
            total = stream.seek(0, 2)
            if start > total:
                return _text(http.HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE,
                             f"{name} has {total} bytes\n")
            stream.seek(start)
            data = stream.read(end - start)
        headers = [("Content-Range", f"bytes {start}-{start + len(data) - 1}/{total}")]
        return _response(http.HTTPStatus.PARTIAL_CONTENT, data, "application/octet-stream",
                         headers)

    def _current(self) -> Path | None:
        current = self.recorder.current_path
        return Path(current) if current is not None else None

    def _file_topics(self, f: files.RecordingFile) -> list[str] | None:
        """The topics of *f*; ``None`` when it cannot be read."""
        if f.path == self._current():
            return list(self.recorder.current_topics)
        key = (f.name, f.size_bytes, f.modified_s)
        topics = self._topics.get(key)
        if topics is None:
            try:
                topics = list(files.describe(f.path)["topics"])
            except (FleetError, OSError):
                return None
            if len(self._topics) >= _MAX_CACHED:
                self._topics.popitem(last=False)
            self._topics[key] = topics
        return topics


def _may_receive(perms: Permissions | None, topics: list[str]) -> bool:
    return perms is None or all(perms.may_receive(t) for t in topics)


def _response(status: http.HTTPStatus, body: bytes, content_type: str,
              extra: list[tuple[str, str]] | None = None) -> Response:
    headers = Headers([("Content-Type", content_type), ("Content-Length", str(len(body))),
                       ("Connection", "close"), ("Cache-Control", "no-store"),
                       *(extra or [])])
    return Response(status.value, status.phrase, headers, body)


def _text(status: http.HTTPStatus, body: str) -> Response:
    return _response(status, body.encode(), "text/plain; charset=utf-8")
