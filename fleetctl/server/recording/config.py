"""The ``recording:`` section of ``server.yaml`` (docs/server.md, "Recording").

Example::

    recording:
      directory: recordings          # relative to server.yaml
      rules:
        - topic: "/husky1/.*"        # RE2, full match
          identities: [husky1]       # whose data; omitted: any sender
        - topic: "/.*/status"
      max_file_bytes: 268435456      # rotate before a file would pass this
      max_file_duration_s: 3600      # rotate after this long
      max_total_bytes: 10737418240   # delete the oldest files past this
      max_age_s: 604800              # delete files older than this; omitted: no age bound
      worker_priority: idle          # the recorder runs on CPU time the relay leaves
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fleetctl.errors import ConfigError
from fleetctl.server.configsection import is_positive_number, section
from fleetctl.server.regex import BadRegex, compile_full

MIB = 1024 * 1024


@dataclass(frozen=True)
class RecordingRule:
    """Record frames on topics matching *topic* sent by one of *identities*.

    Attributes:
        topic: RE2 pattern, full match against the topic.
        identities: Identity names (auth map) whose frames are recorded; empty: any sender.
    """

    topic: str
    identities: tuple[str, ...] = ()


@dataclass(frozen=True)
class RecordingConfig:
    """Where and what the server records, and the bounds of its disk use.

    Attributes:
        directory: Directory of the ``.mcap`` files (created if missing). Every ``.mcap``
            file in it counts toward ``max_total_bytes`` and may be deleted by the bounds.
        rules: A frame is recorded when any rule matches it.
        max_file_bytes: A file is closed and a new one started before a message would
            take it past this, bytes; a single message larger than this is dropped
            (counted ``too_big``). At most half of ``max_total_bytes``.
        max_file_duration_s: A file is closed after this many seconds (also at most
            half of ``max_age_s``, so the age bound deletes data in slices).
        max_total_bytes: Bytes of all files together; the oldest closed files are deleted
            so that the closed files plus a full current file fit.
        max_age_s: Closed files whose last write is older than this are deleted, seconds;
            ``None``: no age bound.
        queue_bytes: Bytes of frames waiting for the writer thread; a frame that does not
            fit is dropped (counted ``queue_full``).
        chunk_bytes: Uncompressed bytes of an MCAP chunk before it is written out.
        flush_interval_s: The chunk in progress is written out and the file flushed at
            least this often, so a reader of the open file lags by at most this, seconds.
        worker_priority: ``idle`` (default): the worker process runs with Linux's
            ``SCHED_IDLE`` policy (niceness 19 elsewhere), only on CPU time the relay
            leaves, so when they compete for a core the recorder falls behind and drops
            (``queue_full``) instead of slowing the relay; ``normal``: the worker competes
            as an equal (recording complete at the relay's expense).
        file_label: Put in every file name (``fleet_<label>_<time>.mcap``); a replica
            sets its cluster name here (not a YAML field), so the fleet's recordings,
            sharded by the replica that accepted each frame, never share a name.
    """

    directory: Path
    rules: tuple[RecordingRule, ...]
    max_file_bytes: int = 256 * MIB
    max_file_duration_s: float = 3600.0
    max_total_bytes: int = 10 * 1024 * MIB
    max_age_s: float | None = None
    queue_bytes: int = 64 * MIB
    chunk_bytes: int = 256 * 1024
    flush_interval_s: float = 1.0
    worker_priority: str = "idle"
    file_label: str | None = None

    @property
    def rotate_after_s(self) -> float:
        """Seconds after which a file is closed: ``max_file_duration_s``, and at most half
        of ``max_age_s``."""
        if self.max_age_s is None:
            return self.max_file_duration_s
        return min(self.max_file_duration_s, self.max_age_s / 2)


_KEYS = {"directory", "rules", "max_file_bytes", "max_file_duration_s", "max_total_bytes",
         "max_age_s", "queue_bytes", "chunk_bytes", "flush_interval_s", "worker_priority"}
_INTS = ("max_file_bytes", "max_total_bytes", "queue_bytes", "chunk_bytes")
_FLOATS = ("max_file_duration_s", "flush_interval_s")


def parse_recording(value: Any, base: Path, path: Path) -> RecordingConfig | None:
    """Validate the ``recording:`` mapping of *path* (``None``: no recording).

    Args:
        value: The parsed YAML value.
        base: Directory relative paths are resolved against (the file's directory).
        path: The config file, for messages.

    Raises:
        ConfigError: A field is invalid; the message names the file and the field.
    """
    value = section(value, _KEYS, "recording", path)
    if value is None:
        return None
    directory = value.get("directory")
    if not isinstance(directory, str) or not directory or "\0" in directory:
        raise ConfigError(f"{path}: field 'recording.directory' is required (a path string "
                          "without a NUL byte)")
    kwargs: dict[str, Any] = {}
    for name in _INTS:
        if name in value:
            kwargs[name] = _positive(value[name], name, path, integer=True)
    for name in _FLOATS:
        if name in value:
            kwargs[name] = float(_positive(value[name], name, path, integer=False))
    if "worker_priority" in value:
        if value["worker_priority"] not in ("idle", "normal"):
            raise ConfigError(f"{path}: field 'recording.worker_priority' must be idle or "
                              "normal")
        kwargs["worker_priority"] = value["worker_priority"]
    if value.get("max_age_s") is not None:
        kwargs["max_age_s"] = float(_positive(value["max_age_s"], "max_age_s", path,
                                              integer=False))
    config = RecordingConfig(base / directory, _rules(value.get("rules"), path), **kwargs)
    if config.max_file_bytes * 2 > config.max_total_bytes:
        raise ConfigError(f"{path}: field 'recording.max_file_bytes' must be at most half of "
                          f"'recording.max_total_bytes' ({config.max_total_bytes}), so "
                          "deleting closed files always makes room for the current one")
    return config


def _positive(v: Any, name: str, path: Path, *, integer: bool) -> int | float:
    if not is_positive_number(v) or (integer and not isinstance(v, int)):
        what = "a positive integer" if integer else "a positive number"
        raise ConfigError(f"{path}: field 'recording.{name}' must be {what}")
    number: int | float = v
    return number


def _rules(value: Any, path: Path) -> tuple[RecordingRule, ...]:
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{path}: field 'recording.rules' must be a non-empty list of "
                          "{topic, identities} mappings")
    rules = []
    for i, item in enumerate(value):
        where = f"recording.rules[{i}]"
        if not isinstance(item, dict):
            raise ConfigError(f"{path}: field '{where}' must be a mapping")
        unknown = sorted(set(item) - {"topic", "identities"}, key=str)
        if unknown:
            raise ConfigError(f"{path}: unknown field '{where}.{unknown[0]}'")
        topic = item.get("topic")
        if not isinstance(topic, str) or not topic:
            raise ConfigError(f"{path}: field '{where}.topic' must be an RE2 regex string")
        try:
            compile_full(topic)
        except BadRegex as exc:
            raise ConfigError(f"{path}: field '{where}.topic': bad RE2 regex {topic!r}: "
                              f"{exc}") from None
        names = item.get("identities", [])
        if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
            raise ConfigError(f"{path}: field '{where}.identities' must be a list of "
                              "identity names")
        rules.append(RecordingRule(topic, tuple(names)))
    return tuple(rules)
