"""The fleet's own message types (``server.yaml`` ``msg_types``) handed to the worker.

The worker decodes what it records, so it needs the definitions the relay loaded. They do
not fit its command line (up to 1000 definitions of 64 KiB; Linux takes 128 KiB per
argument), and its stdin carries the frames: the recorder writes them once to a file of
its own (``mkstemp``: 0600, a new name, no link followed) and passes its path; every
restarted worker reads the same file; :meth:`Recorder.stop` deletes it.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

from fleetctl.server.msgtypes import MsgTypes


def write_types_file(msg_types: MsgTypes) -> Path:
    """A new file holding *msg_types*.

    Raises:
        OSError: The temporary directory cannot be written.
    """
    fd, name = tempfile.mkstemp(prefix="fleetctl-recording-types-", suffix=".json")
    with os.fdopen(fd, "w", encoding="utf-8") as out:
        json.dump([[type_name, text] for type_name, text in msg_types], out)
    return Path(name)


def read_types_file(path: Path) -> MsgTypes:
    """The message types :func:`write_types_file` wrote to *path*.

    Raises:
        OSError: It cannot be read.
        ValueError: It is not such a file.
    """
    data = json.loads(path.read_text(encoding="utf-8"))
    if not isinstance(data, list) or not all(
            isinstance(e, list) and len(e) == 2 and all(isinstance(s, str) for s in e)
            for e in data):
        raise ValueError(f"{path}: not a list of [type, definition] pairs")
    return tuple((name, text) for name, text in data)
