"""fleet.yaml's ``recording:`` section: what a deployed server records, and its disk bounds.

Example::

    recording:
      topics: ["/.*/(map|odom|tf|tf_static)", "/husky1/.*"]   # RE2, full match
      max_total_bytes: 10737418240    # the oldest files go past this (default 10 GiB)
      max_file_bytes: 268435456       # a file is rotated before this (default 256 MiB,
                                      # or half of max_total_bytes when that is less)
      max_age_s: 604800               # files older than this go; omitted: no age bound

It renders into server.yaml's ``recording:`` section (docs/server.md, "Recording") with
``directory: recordings``; ``fleetctl up`` puts that directory on the server's data
volume, so recordings outlive ``down`` as the database does. Who may fetch a file is the
relay's rule: a token whose receive rules cover every topic in it.

Each value is checked as the server checks it (the relay's regex compiler, the file bound
at most half the total bound), so a fleet that validates renders a server.yaml the server
loads.
"""

from __future__ import annotations

from dataclasses import dataclass

import yaml

from fleetctl.deploy.topics import check_regex
from fleetctl.deploy.yamlnodes import Document, FieldPath, FleetInvalid

MIB = 1024 * 1024
DEFAULT_MAX_TOTAL_BYTES = 10 * 1024 * MIB
DEFAULT_MAX_FILE_BYTES = 256 * MIB
MIN_FILE_BYTES = MIB  # a file must hold at least a camera frame or a map
MAX_BYTES = 1 << 50  # 1 PiB: past any disk, and far inside a float's exact integers
MIN_AGE_S = 60
MAX_AGE_S = 100 * 365 * 86400
MAX_TOPICS = 64
_FIELDS = ("max_total_bytes", "max_file_bytes", "max_age_s")


@dataclass(frozen=True)
class FleetRecording:
    """What the fleet's server records.

    Attributes:
        topics: RE2 patterns (full match); a frame on a matching topic is recorded,
            whoever sent it.
        max_total_bytes: Bytes of all recordings together; the oldest go past this.
        max_file_bytes: A file is closed before it would pass this; at most half of
            *max_total_bytes*.
        max_age_s: Files older than this many seconds are deleted; ``None``: no age bound.
    """

    topics: tuple[str, ...]
    max_total_bytes: int = DEFAULT_MAX_TOTAL_BYTES
    max_file_bytes: int = DEFAULT_MAX_FILE_BYTES
    max_age_s: int | None = None


def build_recording(doc: Document, node: yaml.Node) -> FleetRecording | None:
    """Read the optional top-level ``recording`` section (``null``: no recording)."""
    path: FieldPath = ("recording",)
    if doc.is_null(node):
        return None
    f = doc.mapping(node, path, ["topics"], _FIELDS)
    topics = tuple(doc.string(n, (*path, "topics", i))
                   for i, n in enumerate(doc.sequence(f["topics"], (*path, "topics"))))

    def integer(key: str, low: int, high: int) -> int | None:
        return doc.integer(f[key], (*path, key), low, high) if key in f else None

    total = integer("max_total_bytes", 2 * MIN_FILE_BYTES, MAX_BYTES)
    total = DEFAULT_MAX_TOTAL_BYTES if total is None else total
    per_file = integer("max_file_bytes", MIN_FILE_BYTES, MAX_BYTES)
    return FleetRecording(
        topics=topics,
        max_total_bytes=total,
        # Unsaid, it follows a small total (a 100 MB budget: 50 MB files), rather than
        # refusing a default the operator never wrote.
        max_file_bytes=min(DEFAULT_MAX_FILE_BYTES, total // 2) if per_file is None
        else per_file,
        max_age_s=integer("max_age_s", MIN_AGE_S, MAX_AGE_S),
    )


def check_recording(recording: FleetRecording) -> None:
    """Raise :class:`FleetInvalid` unless the server would load this section.

    Also called for a fleet built in code (:func:`fleetctl.deploy.fleet.validate`), so
    the bounds are checked here as well as by the reader.
    """
    path: FieldPath = ("recording",)
    if not recording.topics:
        raise FleetInvalid((*path, "topics"), "list at least one topic pattern (or remove "
                           "the recording section to record nothing)")
    if len(recording.topics) > MAX_TOPICS:
        raise FleetInvalid((*path, "topics"), f"{len(recording.topics)} patterns; at most "
                           f"{MAX_TOPICS} (one pattern can list many topics: /a|/b)")
    for i, topic in enumerate(recording.topics):
        if not topic:
            # It would match only the empty topic, which no frame has; the server refuses it.
            raise FleetInvalid((*path, "topics", i), "empty pattern: give an RE2 regex of "
                               "topics (e.g. /husky1/.*)")
        check_regex(topic, (*path, "topics", i))
    bounds = (("max_total_bytes", recording.max_total_bytes, 2 * MIN_FILE_BYTES, MAX_BYTES),
              ("max_file_bytes", recording.max_file_bytes, MIN_FILE_BYTES, MAX_BYTES))
    for key, value, low, high in bounds:
        if not low <= value <= high:
            raise FleetInvalid((*path, key), f"must be between {low} and {high}, got {value}")
    if recording.max_age_s is not None and not MIN_AGE_S <= recording.max_age_s <= MAX_AGE_S:
        raise FleetInvalid((*path, "max_age_s"), f"must be between {MIN_AGE_S} and "
                           f"{MAX_AGE_S}, got {recording.max_age_s}")
    if recording.max_file_bytes * 2 > recording.max_total_bytes:
        raise FleetInvalid((*path, "max_file_bytes"), f"{recording.max_file_bytes} is more "
                           f"than half of max_total_bytes ({recording.max_total_bytes}): "
                           "deleting closed files must always leave room for the current one")


def dump_recording(recording: FleetRecording) -> dict[str, object]:
    """The section as fleet.yaml writes it (defaults written out, so the file says them)."""
    out: dict[str, object] = {"topics": list(recording.topics),
                              "max_total_bytes": recording.max_total_bytes,
                              "max_file_bytes": recording.max_file_bytes}
    if recording.max_age_s is not None:
        out["max_age_s"] = recording.max_age_s
    return out
