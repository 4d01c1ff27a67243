"""``fleetctl recordings``: list and fetch the server's MCAP recordings.

Two ways to reach them: ``--server URL`` (``GET /recordings`` on the relay port or the
HTTPS port, with a Bearer token from ``--token-file``: the files whose every topic the
token may receive; on the relay port the operator on the server host without a token sees
all), or the recording directory itself on the server host (``--config server.yaml`` or
``--dir``).

Replicas record what their own senders sent (each file name carries the replica's name),
so a fleet's recordings are sharded: ``--server`` given once per replica lists them all
(with a SERVER column; a replica that does not answer is named on stderr while the others
are listed) and ``fetch`` takes the file from whichever replica has it. ``fetch`` writes a
complete, indexed copy, also of the file still being written (read up to its last
flushed chunk), which ``ros2 bag``, rosbags and Foxglove open. ``merge``
(:mod:`fleetctl.cli.recordingmerge`) joins several recordings, e.g. a robot's files on
two replicas after a failover, into one such file.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import typer

from fleetctl.cli.output import OutputFormat, emit, output_option
from fleetctl.cli.reach import ca_context, why_unreachable
from fleetctl.cli.throttled import throttled_error
from fleetctl.cli.tokenfile import read_token_file
from fleetctl.cli.widetable import table_with_names, terminal_columns
from fleetctl.client import loginthrottle
from fleetctl.errors import ConfigError, ConflictError, ExitCode, FleetError
from fleetctl.server.config import ServerConfig, load_server_config
from fleetctl.server.recording import files


@dataclass(frozen=True)
class Recording:
    """One recording file.

    Attributes:
        name: File name in the recording directory.
        path: Full path.
        size_bytes: Size on disk.
        complete: The server finished it (else it is being written, or the server died).
        messages: Messages in it (up to its last flushed chunk when not complete).
        start_ns: Log time of its first message, ns since the epoch (0: no message).
        end_ns: Log time of its last message.
        topics: Its topics, sorted.
    """

    name: str
    path: Path
    size_bytes: int
    complete: bool
    messages: int
    start_ns: int
    end_ns: int
    topics: list[str]


@dataclass(frozen=True)
class Fetched:
    """What ``recordings fetch`` wrote.

    Attributes:
        source: The recording read (a path, or the server's URL of it).
        target: The complete copy written.
        messages: Messages copied.
        still_open: The source was not closed (being written, or its writer stopped):
            the copy ends at its last flush (``flush_interval_s``); a later fetch of a
            file being written gets more.
    """

    source: str
    target: Path
    messages: int
    still_open: bool = False

    def text(self) -> str:
        """One line for the terminal."""
        if self.still_open:
            return (f"wrote {self.target} ({self.messages} messages so far: the file is "
                    "still open (being written); this copy ends at its last flush)")
        return f"wrote {self.target} ({self.messages} messages)"


@dataclass(frozen=True)
class RemoteRecording:
    """One recording as the server lists it.

    Attributes:
        name: File name.
        size_bytes: Size when listed.
        modified_s: Last write, seconds since the epoch.
        complete: Closed by the server (else being written).
        topics: Its topics, sorted.
    """

    name: str
    size_bytes: int
    modified_s: float
    complete: bool
    topics: list[str]
    server: str = ""


@dataclass(frozen=True)
class Remote:
    """How to reach a server's ``/recordings``.

    Attributes:
        url: ``ws(s)://`` or ``http(s)://`` URL of the relay port.
        token: Bearer token, or ``None``. Never shown in a repr.
        ca_file: CA bundle to verify a TLS server with, or ``None`` (the system's).
    """

    url: str
    token: str | None = None
    ca_file: Path | None = None

    def get(self, path: str, byte_range: str | None = None) -> tuple[int, dict[str, str],
                                                                     bytes]:
        """``GET path``; returns status, headers and body.

        Raises:
            RetryLater: 429: too many failed logins from this address (exit 7).
            FleetError: The server cannot be reached, or answered 401/403/404/5xx.
        """
        base = self.url.rstrip("/")
        for ws, plain in (("wss://", "https://"), ("ws://", "http://")):
            if base.startswith(ws):
                base = plain + base[len(ws):]
        try:
            parts = urllib.parse.urlsplit(base)
            parts.port  # noqa: B018  (raises ValueError for a port out of range)
        except ValueError as exc:
            raise ConfigError(f"--server {self.url}: not a URL: {exc}") from None
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ConfigError(f"--server {self.url}: expected a ws://, wss://, http:// or "
                              "https:// URL with a host")
        if parts.query or parts.fragment or base.endswith(("?", "#")):
            # The paths are appended to the URL: a query would swallow them.
            raise ConfigError(f"--server {self.url}: give the server's URL without a ?query "
                              "or #fragment (e.g. https://HOST:8443/)")
        request = urllib.request.Request(base + path)
        if self.token is not None:
            request.add_header("Authorization", f"Bearer {self.token}")
        if byte_range is not None:
            request.add_header("Range", byte_range)
        context = ca_context(self.ca_file)
        try:
            with urllib.request.urlopen(request, timeout=30, context=context) as resp:
                return resp.status, dict(resp.headers), resp.read()
        except urllib.error.HTTPError as exc:
            throttled = loginthrottle.from_response(exc.code, exc.headers, time.time())
            if throttled is not None:
                raise throttled_error(f"{self.url}: GET {path}", throttled) from None
            detail = _without_request_line(exc.read().decode("utf-8", "replace").strip(),
                                           path)
            if exc.code == 401 and self.token is None:
                detail += " (give it with --token-file FILE)"
            # A token the fleet refuses is the caller's to fix (exit 3, as `replay`).
            code = ExitCode.CONFIG if exc.code in (401, 403) else None
            raise FleetError(f"{self.url}: GET {path}: {exc.code} {detail}",
                             exit_code=code) from None
        except (urllib.error.URLError, OSError) as exc:
            reason = getattr(exc, "reason", exc)
            raise FleetError(f"--server {self.url}: "
                             f"{why_unreachable(reason, parts.scheme)}") from None


def _without_request_line(detail: str, path: str) -> str:
    """The server's reason without the ``GET /path`` it starts with (some answers say
    it; the error already does)."""
    said = f"GET {path}"
    return detail[len(said):].lstrip(": ") if detail.startswith(said) else detail


def list_remote(remote: Remote) -> list[RemoteRecording]:
    """The recordings the server shows this caller (``GET /recordings``).

    Raises:
        FleetError: The server cannot be reached or refused.
    """
    _status, _headers, body = remote.get("/recordings")
    try:
        data: Any = json.loads(body)
        return [RemoteRecording(r["name"], int(r["bytes"]), float(r["modified_s"]),
                                bool(r["complete"]), list(r["topics"]), remote.url)
                for r in data["recordings"]]
    except (ValueError, KeyError, TypeError) as exc:
        raise FleetError(f"{remote.url}: GET /recordings: not a recordings list "
                         f"({exc})") from None


def list_replicas(remotes: list[Remote]) -> tuple[list[RemoteRecording], list[str]]:
    """Every replica's recordings, oldest last write first, and the errors of those that
    did not answer.

    Raises:
        FleetError: None of them answered (the first one's error).
    """
    found: list[RemoteRecording] = []
    errors: list[FleetError] = []
    for remote in remotes:
        try:
            found += list_remote(remote)
        except FleetError as exc:
            errors.append(exc)
    if errors and len(errors) == len(remotes):
        raise errors[0]
    found.sort(key=lambda r: (r.modified_s, r.name))
    return found, [str(e) for e in errors]


def fetch_from_replicas(remotes: list[Remote], name: str, target: Path) -> Fetched:
    """Fetch *name* from the first replica that has it (a 404 means: not this one).

    Raises:
        FleetError: No replica has it (or may show it to this token), or a fetch failed.
        ConflictError: The target file exists.
    """
    missing: list[str] = []
    for remote in remotes:
        try:
            return fetch_remote(remote, name, target)
        except FleetError as exc:
            if ": 404 " not in str(exc):
                raise
            missing.append(remote.url)
    where = (f"is not on {missing[0]}" if len(missing) == 1
             else f"is on none of {', '.join(missing)}")
    # A name listed a minute ago may be gone: the bounds delete the oldest files.
    raise FleetError(f"recording {name!r} {where} (or this token may not "
                     "receive all of its topics); the server deletes the oldest files past "
                     "its disk bounds: see `fleetctl recordings list`")


def fetch_remote(remote: Remote, name: str, target: Path) -> Fetched:
    """Download recording *name* in ranges, then write a complete copy to *target* (a
    directory: ``target/name``).

    The download goes to a temp file with a random name (``mkstemp``: ``O_EXCL``, so a
    link planted beside the target is never opened), and the finished file is linked to
    *target*, which never replaces anything there.

    Raises:
        FleetError: Bad name (exit 2), the server refused, the download failed, or the
            target cannot be written (exit 5).
        ConflictError: The target file exists.
    """
    check_name(name)
    target = _target_file(target, name)
    fd, part = open_part(target)
    try:
        with os.fdopen(fd, "wb") as out:
            offset, total = 0, None
            while total is None or offset < total:
                _status, headers, body = remote.get(f"/recordings/{name}",
                                                    f"bytes={offset}-")
                total = int(headers.get("Content-Range", "/0").rpartition("/")[2])
                if not body:
                    break
                out.write(body)
                offset += len(body)
        source = f"{remote.url.rstrip('/')}/recordings/{name}"
        if files.is_complete(part):
            part.chmod(new_file_mode())  # as the copy of an open file gets (mkstemp: 0600)
            link_new(part, target)
            return Fetched(source, target, files.describe(target)["messages"])
        return Fetched(source, target, files.export(part, target), still_open=True)
    except OSError as exc:
        raise cannot_write(target, exc) from None
    finally:
        part.unlink(missing_ok=True)


def _target_file(target: Path, name: str) -> Path:
    """``target/name`` for a directory *target*; refuses one that exists (a link too).

    Raises:
        ConflictError: It exists (a dangling symbolic link included).
    """
    target = target / name if target.is_dir() else target
    if os.path.lexists(target):
        raise ConflictError(f"{target}: already exists")
    return target


def link_new(source: Path, target: Path) -> None:
    """Give *source* the name *target* too, never replacing what is there."""
    try:
        os.link(source, target, follow_symlinks=False)
    except FileExistsError:
        raise ConflictError(f"{target}: already exists") from None
    except OSError:  # no hard links on this file system: a rename, after the check
        if os.path.lexists(target):
            raise ConflictError(f"{target}: already exists") from None
        source.rename(target)


def new_file_mode() -> int:
    """The mode ``open()`` gives a new file under the current umask."""
    mask = os.umask(0o077)
    os.umask(mask)
    return 0o666 & ~mask


def cannot_write(target: Path, exc: OSError) -> FleetError:
    """The error for a *target* that cannot be written (exit 5)."""
    return FleetError(f"{target}: cannot write: {exc.strerror or exc}",
                      exit_code=ExitCode.ENVIRONMENT)


def open_part(target: Path) -> tuple[int, Path]:
    """A new temp file beside *target* (0600, a dot name ending ``.part``), to be renamed or
    linked into place when whole: its descriptor and path.

    Raises:
        FleetError: The directory cannot be written (exit 5).
    """
    try:
        fd, temp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part",
                                    dir=target.parent)
    except OSError as exc:
        raise cannot_write(target, exc) from None
    return fd, Path(temp)


def check_name(name: str) -> None:
    """Refuse a recording name that is not a plain file name (usage, exit 2)."""
    if "/" in name or name in ("", ".", ".."):
        raise FleetError(f"recording name {name!r}: give a file name from "
                         "`fleetctl recordings list`", exit_code=ExitCode.USAGE)


def check_one_source(config: Path | None, directory: Path | None,
                     server: list[str] | None) -> None:
    """Refuse more than one of ``--config``, ``--dir`` and ``--server`` (one was used, the
    others silently ignored).

    Raises:
        FleetError: (usage, exit code 2) naming the options given.
    """
    given = [name for name, value in (("--config", config), ("--dir", directory),
                                      ("--server", server)) if value]
    if len(given) > 1:
        raise FleetError(f"{' and '.join(given)} given: use one of --config, --dir and "
                         "--server", exit_code=ExitCode.USAGE)


def recording_dir(config: Path | None, directory: Path | None) -> Path:
    """The recording directory from ``--dir``, else from ``--config``'s ``recording:``.

    A ``--config`` whose directory is not there yet has no recordings (the server makes it
    when it records); a ``--dir`` that is not there is a mistyped path.

    Raises:
        ConfigError: Neither is given, ``--dir`` is not a directory, the config is invalid
            or has no ``recording:``.
        FleetError: (usage) both are given.
    """
    check_one_source(config, directory, None)
    if directory is not None:
        if not directory.is_dir():
            what = ("is not a directory" if os.path.lexists(directory)
                    else "no such directory")
            raise ConfigError(f"--dir {directory}: {what}")
        return directory
    if config is None:
        raise ConfigError("give --server URL (the HTTPS port, with --token-file and "
                          "--ca-file), --config server.yaml or --dir DIR")
    server = load_server_config(config)
    recording = server.recording
    if recording is None:
        raise ConfigError(f"{config}: field 'recording' is not set: the server records "
                          "nothing")
    from fleetctl.deploy.compose import COMPOSE_DIR, STATE_FILE

    fleet_dir = config.resolve().parent.parent
    if (not recording.directory.exists() and config.resolve().parent.name == "server"
            and (fleet_dir / COMPOSE_DIR / STATE_FILE).is_file()):
        # A fleet's own server.yaml, deployed with `fleetctl up`: its server records into
        # its data volume, and this directory never fills ("no recordings" said otherwise).
        raise ConfigError(f"--config {config}: this fleet runs with `fleetctl up`, whose "
                          f"server records into its data volume, not {recording.directory}: "
                          f"ask it with {_deployed_options(fleet_dir, server)}")
    return recording.directory


def _deployed_options(fleet_dir: Path, server: ServerConfig) -> str:
    """``--server URL --token-file FILE --ca-file CERT`` for the fleet's deployment, with
    the URL ``fleetctl up`` printed (the endpoint's host, the published port); a generic
    ``https://HOST:PORT/`` when its state cannot be read."""
    from fleetctl.deploy.composerun import deployed_recordings_options

    try:
        return deployed_recordings_options(fleet_dir)
    except FleetError:
        from fleetctl.deploy.fleet import DEFAULT_HTTPS_PORT
        from fleetctl.deploy.tls import CERT_RELPATH

        port = server.web.listen_port if server.web is not None else DEFAULT_HTTPS_PORT
        return (f"--server https://HOST:{port}/ --token-file FILE "
                f"--ca-file {fleet_dir / CERT_RELPATH}")


def list_recordings(directory: Path) -> list[Recording]:
    """Every recording in *directory*, oldest first.

    Raises:
        FleetError: A file cannot be read or is not MCAP (the message names it).
    """
    out = []
    for f in files.scan(directory):
        info = files.describe(f.path)
        out.append(Recording(f.name, f.path, f.size_bytes, info["complete"],
                             info["messages"], info["start_ns"], info["end_ns"],
                             info["topics"]))
    return out


def fetch(directory: Path, name: str, target: Path) -> Fetched:
    """Write a complete, indexed copy of recording *name* to *target* (a directory:
    ``target/name``).

    Raises:
        FleetError: No such recording; *name* is not a plain file name.
        ConflictError: The target file exists.
    """
    check_name(name)
    source = directory / name
    if not source.is_file():
        raise FleetError(f"{source}: no such recording (see `fleetctl recordings list`)")
    target = _target_file(target, name)
    open_now = not files.is_complete(source)
    return Fetched(str(source), target, files.export(source, target), still_open=open_now)


def _remote_text(found: list[RemoteRecording], urls: list[str], width: int | None) -> str:
    if not found:
        return f"no recordings on {', '.join(urls)} (that this token may receive)"
    rows: list[tuple[object, ...]] = [
        (r.name, r.size_bytes, dt.datetime.fromtimestamp(r.modified_s, dt.UTC).strftime(
            "%Y-%m-%d %H:%M:%S"), "yes" if r.complete else "writing") for r in found]
    head: tuple[str, ...] = ("NAME", "BYTES", "LAST WRITE (UTC)", "COMPLETE")
    if len(urls) > 1:  # before TOPICS, the column cut to the width
        head, rows = (*head, "SERVER"), [(*row, r.server) for row, r in
                                         zip(rows, found, strict=True)]
    return table_with_names((*head, "TOPICS"), rows, [r.topics for r in found], width,
                            "topics")


def _time(ns: int) -> str:
    if not ns:
        return "-"
    return dt.datetime.fromtimestamp(ns / 1e9, dt.UTC).strftime("%Y-%m-%d %H:%M:%S")


def _list_text(found: list[Recording], directory: Path, width: int | None) -> str:
    if not found:
        return f"no recordings in {directory}"
    rows = [(r.name, r.size_bytes, r.messages, _time(r.start_ns), _time(r.end_ns),
             "yes" if r.complete else "writing") for r in found]
    return table_with_names(("NAME", "BYTES", "MESSAGES", "START (UTC)", "END (UTC)",
                             "COMPLETE", "TOPICS"), rows, [r.topics for r in found], width,
                            "topics")


_CONFIG = typer.Option(None, "--config", "-c", help="server.yaml (its recording.directory).")
_DIR = typer.Option(None, "--dir", "-d", help="The recording directory (instead of --config).")
_SERVER = typer.Option(None, "--server", "-s", help="ws(s):// or http(s):// URL of the relay "
                       "port or the HTTPS port (`fleetctl up`'s): ask the server (instead of "
                       "--config/--dir); once per replica for a fleet of replicas.")
_TOKEN = typer.Option(None, "--token-file", help="File holding a Bearer token (--server).")
_CA = typer.Option(None, "--ca-file", help="CA bundle for a wss:// server (--server).")
_ALL_TOPICS = typer.Option(False, "--all-topics", help="Every topic of each file in the "
                           "TOPICS column, however wide (default: as many as fit the "
                           "terminal, then '+N more'; -o json has them all).")


def register(app: typer.Typer) -> None:
    """Add the ``recordings`` command group to *app*."""
    rec_app = typer.Typer(help="MCAP recordings of the server: list, fetch, merge.",
                          no_args_is_help=True)

    @rec_app.command("list")
    def list_command(config: Path | None = _CONFIG, directory: Path | None = _DIR,
                     server: list[str] | None = _SERVER, token_file: Path | None = _TOKEN,
                     ca_file: Path | None = _CA, all_topics: bool = _ALL_TOPICS,
                     output: OutputFormat = output_option()) -> None:
        """List the recordings (oldest first), the one being written included."""
        check_one_source(config, directory, server)
        width = None if all_topics else terminal_columns()
        if server:
            token = read_token_file(token_file)
            listed, errors = list_replicas([Remote(u, token, ca_file) for u in server])
            for error in errors:
                typer.echo(f"fleetctl: not listed: {error}", err=True)
            emit(listed, output, lambda: _remote_text(listed, server, width))
            return
        where = recording_dir(config, directory)
        found = list_recordings(where)
        emit(found, output, lambda: _list_text(found, where, width))

    @rec_app.command("fetch")
    def fetch_command(
        name: str = typer.Argument(..., help="Recording file name (see `recordings list`)."),
        to: Path = typer.Option(Path("."), "--to", help="Target file or directory."),
        config: Path | None = _CONFIG, directory: Path | None = _DIR,
        server: list[str] | None = _SERVER, token_file: Path | None = _TOKEN,
        ca_file: Path | None = _CA, output: OutputFormat = output_option(),
    ) -> None:
        """Write a complete, indexed copy of a recording (also of the open one)."""
        check_one_source(config, directory, server)
        if server:
            token = read_token_file(token_file)
            result = fetch_from_replicas([Remote(u, token, ca_file) for u in server], name, to)
        else:
            result = fetch(recording_dir(config, directory), name, to)
        emit(result, output, result.text)

    @rec_app.command("merge")
    def merge_command(
        names: list[str] | None = typer.Argument(None, help="Recordings to merge: file "
                                                 "names with --server/--dir/--config (see "
                                                 "`recordings list`), else paths; none: "
                                                 "every file --robot/--since/--until select."),
        to: Path = typer.Option(..., "--to", help="The merged .mcap file to write."),
        robot: str | None = typer.Option(None, "--robot", help="Only this robot's topics "
                                         "(/NAME/...), from the files that have them."),
        since: str | None = typer.Option(None, "--since", help="Leave out messages logged "
                                         "before this (the newest latched message of each "
                                         "topic and a camera's frames from its last keyframe "
                                         "are carried to it): seconds since the epoch or ISO "
                                         "8601 (2026-12-06T19:00:00Z; UTC without an "
                                         "offset)."),
        until: str | None = typer.Option(None, "--until", help="Leave out messages logged "
                                         "after this (same forms)."),
        force: bool = typer.Option(False, "--force", help="Replace the --to file if it "
                                   "exists."),
        config: Path | None = _CONFIG, directory: Path | None = _DIR,
        server: list[str] | None = _SERVER, token_file: Path | None = _TOKEN,
        ca_file: Path | None = _CA, output: OutputFormat = output_option(),
    ) -> None:
        """Merge recordings (replicas, rotated files) into one indexed MCAP file.

        Messages in log-time order; channels and schemas deduplicated; a
        message recorded twice written once; an open file read up to its last
        flush."""
        from fleetctl.cli.recordingmerge import merge_command, parse_time
        from fleetctl.server.recording.merge import Selection

        check_one_source(config, directory, server)
        selection = Selection(robot, None if since is None else parse_time(since, "--since"),
                              None if until is None else parse_time(until, "--until"))
        token = read_token_file(token_file) if server else None
        result = merge_command(names or [], to, selection,
                               remotes=[Remote(u, token, ca_file) for u in server or []],
                               directory=directory, config=config, force=force)
        emit(result, output, result.text)

    app.add_typer(rec_app, name="recordings")
