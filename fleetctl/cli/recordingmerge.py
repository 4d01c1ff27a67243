"""``fleetctl recordings merge``: one indexed MCAP file from several recordings.

Which recordings: file names (on the replicas given with ``--server``, fetched as
``fetch`` does; in ``--dir``/``--config``'s directory; else paths on this host), and/or a
selection: ``--robot NAME`` (the files with that robot's topics, and only those topics
merged) and ``--since``/``--until`` (log times outside are left out, but the window starts
with the newest latched message of each channel and the current video group from before
``--since``, as a rotated file starts with their copies). The merge itself is
:mod:`fleetctl.server.recording.merge`; this module finds the inputs, fetches them into a
scratch directory beside the output and puts the result in place (written to a temp file
in the same directory, then linked to its name, or renamed over an old file with
``--force``).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
import re
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from fleetctl.cli.recordings import (
    Remote,
    RemoteRecording,
    cannot_write,
    check_name,
    fetch_from_replicas,
    fetch_remote,
    link_new,
    list_remote,
    open_part,
    recording_dir,
)
from fleetctl.errors import ConflictError, ExitCode, FleetError
from fleetctl.server.recording import files
from fleetctl.server.recording.merge import MergeSource, Selection, merge

CLOCK_SLACK_S = 600.0
"""Log times are the robots' clocks, file names and last writes the server's: a file is
left out by its name or last write only when it is this far outside the window."""
MERGED_FILE_MODE = 0o644  # a recording, not a secret
# fleet_[LABEL_]YYYYmmddTHHMMSSZ[-N].mcap (fleetctl.server.recording.files.new_path)
_STAMP = re.compile(r"_(\d{8}T\d{6}Z)(?:-\d+)?\.mcap$")


@dataclass(frozen=True)
class Merged:
    """What ``recordings merge`` wrote.

    Attributes:
        target: The merged file.
        files: Recordings read.
        sources: Their names (paths, or ``URL/recordings/NAME``).
        messages: Messages written.
        duplicates: Messages recorded twice (same log time) written once.
        repeats: Start-of-file copies of latched or video messages whose original is in
            the merged file (left out).
        carried: Of ``messages``, those from before ``--since`` written at its time (each
            latched channel's newest message, each video channel's frames since its last
            keyframe).
        not_carried: Video topics whose frames before ``--since`` were not carried (no
            keyframe found within the bound): they show from their next keyframe.
        topics: Topics written, sorted.
        start_ns: Log time of the first message, ns since the epoch.
        end_ns: Log time of the last.
        still_open: Sources without a footer (being written, or cut short): read up to
            their last flushed chunk.
    """

    target: Path
    files: int
    sources: list[str]
    messages: int
    duplicates: int
    repeats: int
    carried: int
    not_carried: list[str]
    topics: list[str]
    start_ns: int
    end_ns: int
    still_open: list[str]

    def text(self) -> str:
        """Lines for the terminal."""
        lines = [f"wrote {self.target}: {self.messages} messages on {len(self.topics)} "
                 f"topic(s), {_utc(self.start_ns)} to {_utc(self.end_ns)} UTC, from "
                 f"{self.files} recording(s)"]
        if self.carried:
            lines.append(f"  carried: {self.carried} message(s) from before --since "
                         "(latched: the newest of each; video: since the last keyframe), "
                         "at its time")
        lines += [f"  {t}: not carried (no keyframe found before --since): shows from its "
                  "next keyframe" for t in self.not_carried]
        if self.duplicates or self.repeats:
            lines.append(f"  left out: {self.duplicates} recorded twice, {self.repeats} "
                         "start-of-file copies of latched/video messages")
        lines += [f"  {s}: still open (being written, or cut short): read up to its last "
                  "flush" for s in self.still_open]
        return "\n".join(lines)


def _utc(ns: int) -> str:
    return dt.datetime.fromtimestamp(ns / 1e9, dt.UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]


def parse_time(value: str, option: str) -> int:
    """*value* as ns since the epoch: seconds since the epoch (``1764000000.5``) or an
    ISO 8601 time (``2026-12-06T19:00:00Z``, ``2026-12-06 19:00:00``: UTC when it names no
    offset, as ``recordings list`` prints them).

    Raises:
        FleetError: (usage, exit 2) neither, naming *option*.
    """
    text = value.strip()
    if re.fullmatch(r"[0-9]{1,12}(\.[0-9]{1,9})?", text):
        whole, _, frac = text.partition(".")
        return int(whole) * 1_000_000_000 + int((frac or "0").ljust(9, "0"))
    try:
        when = dt.datetime.fromisoformat(text)
    except ValueError:
        raise FleetError(f"{option} {value!r}: not a time: give seconds since the epoch or "
                         "an ISO 8601 time (2026-12-06T19:00:00Z; UTC without an offset)",
                         exit_code=ExitCode.USAGE) from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=dt.UTC)
    delta = when - dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1000


def check_selection(selection: Selection) -> None:
    """Refuse a window that ends before it starts, or a robot name with a ``/``.

    Raises:
        FleetError: (usage, exit 2) naming the options.
    """
    since, until = selection.since_ns, selection.until_ns
    if since is not None and until is not None and until < since:
        raise FleetError(f"--until {_utc(until)} is before --since {_utc(since)}",
                         exit_code=ExitCode.USAGE)
    if selection.robot is not None and ("/" in selection.robot or not selection.robot):
        raise FleetError(f"--robot {selection.robot!r}: give a robot's name (the first "
                         "segment of its topics: husky1 for /husky1/scan)",
                         exit_code=ExitCode.USAGE)


def selected_remote(found: RemoteRecording, selection: Selection) -> bool:
    """Whether a listed file may hold selected messages (its topics; its start time, from
    its name, and its last write against the window, with :data:`CLOCK_SLACK_S`)."""
    if not any(selection.wants(t) for t in found.topics):
        return False
    slack_ns = int(CLOCK_SLACK_S * 1e9)
    if selection.since_ns is not None and (
            int(found.modified_s * 1e9) + slack_ns < selection.since_ns):
        return False
    stamp = _STAMP.search(found.name)
    if stamp is not None and selection.until_ns is not None:
        started = dt.datetime.strptime(stamp.group(1), "%Y%m%dT%H%M%SZ").replace(
            tzinfo=dt.UTC)
        return int(started.timestamp() * 1e9) - slack_ns <= selection.until_ns
    return True


def remote_sources(remotes: Sequence[Remote], names: Sequence[str], selection: Selection,
                   scratch: Path) -> list[MergeSource]:
    """Fetch the named files (from whichever replica has each) or, without names, every
    selected file of every replica, into *scratch*.

    Raises:
        FleetError: A replica cannot be reached or refused (named: the merge would miss
            its part of the run), or a named file is on none of them.
    """
    sources = []
    for n, name in enumerate(names):
        fetched = fetch_from_replicas(list(remotes), name, _subdir(scratch, f"name{n}"))
        sources.append(MergeSource(fetched.target, fetched.source, fetched.still_open))
    if names:
        return sources
    for n, remote in enumerate(remotes):
        into = _subdir(scratch, f"server{n}")
        for found in list_remote(remote):
            if selected_remote(found, selection):
                fetched = fetch_remote(remote, found.name, into)
                sources.append(MergeSource(fetched.target, fetched.source,
                                           fetched.still_open))
    return sources


def _subdir(scratch: Path, name: str) -> Path:
    path = scratch / name
    path.mkdir()
    return path


def directory_sources(directory: Path, names: Sequence[str],
                      selection: Selection) -> list[MergeSource]:
    """The named files of *directory* or, without names, its files that hold selected
    topics in the window (read from their summaries, or the open file itself).

    Raises:
        FleetError: A named file is not there; a file cannot be read or is not MCAP.
    """
    if names:
        for name in names:
            check_name(name)
        return [MergeSource(directory / n, str(directory / n)) for n in names]
    return [MergeSource(f.path, str(f.path)) for f in files.scan(directory)
            if _holds_selected(f.path, selection)]


def _holds_selected(path: Path, selection: Selection) -> bool:
    info = files.describe(path)
    if not info["messages"] or not any(selection.wants(t) for t in info["topics"]):
        return False
    return ((selection.since_ns is None or info["end_ns"] >= selection.since_ns)
            and (selection.until_ns is None or info["start_ns"] <= selection.until_ns))


@contextlib.contextmanager
def scratch_beside(target: Path) -> Iterator[Path]:
    """A temporary directory in *target*'s directory (fetched and exported copies: the
    disk the result goes to), removed on exit.

    Raises:
        FleetError: *target*'s directory cannot be written (exit 5).
    """
    try:
        holder = tempfile.TemporaryDirectory(prefix=".fleetctl-merge-", dir=target.parent)
    except FileNotFoundError:
        raise FleetError(f"{target}: cannot write: no such directory {target.parent}",
                         exit_code=ExitCode.ENVIRONMENT) from None
    except OSError as exc:
        raise cannot_write(target, exc) from None
    with holder as scratch:
        yield Path(scratch)


def check_target(target: Path, force: bool) -> None:
    """Refuse a *target* that is a directory, or that exists without *force*.

    Raises:
        FleetError: (usage, exit 2) a directory.
        ConflictError: It exists (a dangling link included) and not *force*.
    """
    if target.is_dir():
        raise FleetError(f"--to {target}: is a directory; give the merged file's name "
                         f"({target / 'merged.mcap'})", exit_code=ExitCode.USAGE)
    if not force and os.path.lexists(target):
        raise ConflictError(f"{target}: already exists (give --force to replace it)")


def check_outside(target: Path, recordings: Path) -> None:
    """Refuse a *target* in the recording directory the merge reads.

    The relay's retention counts every ``.mcap`` there against its byte bound and deletes
    the oldest first, ``recordings list`` and ``fetch`` would show the merged file as a
    recording, and a later merge of the directory would read its messages again.

    Raises:
        FleetError: (usage, exit 2) naming both.
    """
    if target.absolute().parent.resolve() == recordings.absolute().resolve():
        raise FleetError(f"--to {target}: is in the recording directory {recordings} it "
                         "merges from, where the relay's retention would count it and "
                         "delete it, and later merges would read it again; write it "
                         "elsewhere", exit_code=ExitCode.USAGE)


def write_merged(sources: Sequence[MergeSource], target: Path, selection: Selection,
                 scratch: Path, force: bool = False) -> Merged:
    """Merge *sources* into a temp file beside *target*, then put it in place.

    Raises:
        ConflictError: *target* exists and not *force*.
        FleetError: An input is bad (named), the selection holds no message, or *target*
            cannot be written (exit 5).
    """
    check_target(target, force)
    if not sources:
        raise FleetError(f"no recording{_selection_text(selection)}")
    fd, part = open_part(target)
    try:
        with os.fdopen(fd, "wb") as out:
            counts = merge(sources, out, selection, scratch)
        if counts.messages == counts.carried:  # only what came before the window
            raise FleetError(f"no message{_selection_text(selection)} in "
                             f"{', '.join(s.label for s in sources)}")
        part.chmod(MERGED_FILE_MODE)  # mkstemp made it 0600
        if force:
            part.replace(target)
        else:
            link_new(part, target)
    except OSError as exc:
        raise cannot_write(target, exc) from None
    finally:
        part.unlink(missing_ok=True)
    return Merged(target, len(sources), [s.label for s in sources], counts.messages,
                  counts.duplicates, counts.repeats, counts.carried, counts.not_carried,
                  counts.topics, counts.start_ns, counts.end_ns, counts.still_open)


def _selection_text(selection: Selection) -> str:
    parts = []
    if selection.robot is not None:
        parts.append(f" of robot {selection.robot!r} (topics /{selection.robot}/...)")
    if selection.since_ns is not None:
        parts.append(f" since {_utc(selection.since_ns)} UTC")
    if selection.until_ns is not None:
        parts.append(f" until {_utc(selection.until_ns)} UTC")
    return "".join(parts)


def merge_command(names: Sequence[str], target: Path, selection: Selection, *,
                  remotes: Sequence[Remote], directory: Path | None, config: Path | None,
                  force: bool) -> Merged:
    """Find the inputs (``--server``, ``--dir``/``--config`` or paths) and merge them.

    Raises:
        FleetError: No input given, or any error of the steps (named, never a traceback).
    """
    check_selection(selection)
    if not names and not remotes and directory is None and config is None:
        raise FleetError("give the recordings to merge: file names with --server, --dir "
                         "or --config (or none, with --robot/--since/--until, for every "
                         "file they select), or paths of .mcap files",
                         exit_code=ExitCode.USAGE)
    check_target(target, force)  # before fetching anything
    recordings = None if remotes or (directory is None and config is None) else (
        recording_dir(config, directory))
    if recordings is not None:
        check_outside(target, recordings)
    with scratch_beside(target) as scratch:
        if remotes:
            sources = remote_sources(remotes, names, selection, scratch)
        elif recordings is not None:
            sources = directory_sources(recordings, names, selection)
        else:
            sources = [MergeSource(Path(n), n) for n in names]
        return write_merged(sources, target, selection, scratch, force)
