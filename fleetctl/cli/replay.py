"""``fleetctl replay FILE --server URL``: play an MCAP recording into a fleet.

The recording's CDR messages are decoded with the file's own ``ros2msg`` schemas, encoded
as fleetctl frames and sent through the robot client's transport
(:class:`fleetctl.client.transport.RobotLink`: fragments, scheduling, reconnects), as the
robot identity the token (or the source address) names, so the web page, Foxglove and
every subscriber see them live. Messages are paced by their log times divided by
``--rate``; each frame is stamped with the wall clock at sending (the viewers show live
data, not the recording's age) and its recorded sequence number.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import typer
from rosbags.typesys import get_types_from_msg
from websockets.exceptions import InvalidURI
from websockets.uri import parse_uri

from fleetctl.cli import replaytopics
from fleetctl.cli.output import OutputFormat, emit, output_option, warn
from fleetctl.cli.reach import ca_context, why_unreachable
from fleetctl.cli.replayfiles import recording_files
from fleetctl.cli.throttled import throttled_error
from fleetctl.cli.tokenfile import read_token_file
from fleetctl.client.config import ClientConfig
from fleetctl.client.transport import (
    REFUSAL_RECORD,
    REFUSED_TOPIC_RECORD,
    UNREACHABLE_RECORD,
    RobotLink,
)
from fleetctl.deploy.replaynames import recorded_prefix, replay_prefix
from fleetctl.deploy.topics import TOPIC
from fleetctl.errors import ConfigError, ExitCode, FleetError
from fleetctl.server.recording import files
from fleetctl.server.recording.latched import is_latched
from fleetctl.wire.codec import Codec
from fleetctl.wire.errors import WireError
from fleetctl.wire.registry import TypeRegistry

_ROBOT_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,62}")  # as client.yaml's robot_name
# Why: the link's no_drop FIFO is bounded; replay waits while half of it is in use.
_QUEUE_HIGH_FRACTION = 0.5
_DRAIN_POLL_S = 0.01
_DRAIN_TIMEOUT_S = 30.0
_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReplayOptions:
    """How to replay.

    Attributes:
        server_url: ``ws://`` or ``wss://`` URL of the fleet server.
        rate: Speed factor: 1 real time, 2 twice as fast; ``None``: as fast as the link
            takes them.
        token: Bearer token of the identity sending, or ``None`` (identified by source
            address). Never shown in a repr.
        robot_name: Name of the replaying robot (its server session).
        remap: ``(old_prefix, new_prefix)`` topic renames, first match wins.
        no_drop: Send every message reliably and in order (else latest-only per topic,
            as a live robot's sensor topics).
        ca_file: CA bundle to verify a ``wss://`` server with (a fleet's self-signed
            certificate); ``None``: the system's CAs.
        onto_live_robots: Send the topics no *remap* matches under their recorded names
            (onto the robots online); else under names no live robot has
            (``/husky1/goal_pose`` as ``/husky1_replay/goal_pose``:
            :mod:`fleetctl.cli.replaytopics`).
    """

    server_url: str
    rate: float | None = 1.0
    token: str | None = field(default=None, repr=False)
    robot_name: str = "replay"
    remap: tuple[tuple[str, str], ...] = ()
    no_drop: bool = True
    ca_file: Path | None = None
    onto_live_robots: bool = False


@dataclass
class ReplayResult:
    """What a replay sent.

    Attributes:
        file: The recording.
        messages: Messages offered to the link.
        topics: Messages per (remapped) topic.
        duration_s: Wall-clock seconds the replay took.
        skipped: Messages skipped (a type without a usable schema), per type.
        dropped: Messages the link dropped: stale ones under ``--latest-only`` (by
            design), or no_drop ones that overflowed its FIFO (then the replay fails).
        renamed: The recorded prefixes sent under a replay's name, to that name
            (``{"/husky1": "/husky1_replay"}``; empty with ``onto_live_robots``).
    """

    file: Path
    messages: int = 0
    topics: dict[str, int] = field(default_factory=dict)
    duration_s: float = 0.0
    skipped: dict[str, int] = field(default_factory=dict)
    dropped: int = 0
    renamed: dict[str, str] = field(default_factory=dict)


class _Decoder:
    """CDR -> message objects with the recording's schemas (types the default registry
    lacks are added from them)."""

    def __init__(self) -> None:
        self.registry = TypeRegistry.default()
        self.codec = Codec(self.registry)
        self._bad: set[str] = set()

    def usable(self, type_name: str, schema_data: bytes | None) -> bool:
        if type_name in self._bad:
            return False
        if type_name in self.registry:
            return True
        try:
            if not schema_data:
                raise WireError("no schema in the file")
            types = get_types_from_msg(schema_data.decode(), type_name)
            self.registry.typestore.register(
                {k: v for k, v in types.items() if k not in self.registry.typestore.fielddefs})
            self.registry.get(type_name)
        except Exception:  # rosbags' parser errors, WireError: the type is skipped
            self._bad.add(type_name)
            return False
        return True

    def frame(self, rec: _Recorded, topic: str, no_drop: bool) -> bytes:
        msg = self.registry.typestore.deserialize_cdr(rec.cdr, rec.type_name)
        # A latched topic (a map, /tf_static) is sent latched, so the relay keeps it for
        # pages and robots that come later, as it does for a live robot's.
        return self.codec.encode(msg, rec.type_name, topic, no_drop=no_drop,
                                 publish_time_ns=time.time_ns(), seq=rec.seq,
                                 latched=rec.latched)


class _Recorded(NamedTuple):
    topic: str
    type_name: str
    schema: bytes | None
    log_ns: int
    cdr: bytes
    seq: int
    latched: bool


def _messages(path: Path) -> Iterator[_Recorded]:
    """The messages of the file (or of the bag directory's files, one after another)
    in file order.

    Raises:
        files.DamagedRecording: A record cannot be read (what came before it was yielded).
    """
    for recording in recording_files(path):
        latched: dict[int, bool] = {}  # channel ids are the file's own
        for schema, channel, message in files.read_messages(recording):
            if channel.id not in latched:
                latched[channel.id] = is_latched(channel.metadata)
            yield _Recorded(channel.topic, schema.name if schema is not None else "",
                            schema.data if schema is not None else None, message.log_time,
                            message.data, message.sequence, latched[channel.id])


async def replay(path: Path, options: ReplayOptions,
                 say: Callable[[str], None] = _log.warning) -> ReplayResult:
    """Play *path* into the fleet at *options.server_url*; return when every frame was
    sent (and, with ``no_drop``, acknowledged by the server).

    *path* is an MCAP file, or a rosbag2 bag directory (its ``.mcap`` files, in order:
    :mod:`fleetctl.cli.replayfiles`). Once the server is reached, *say* gets the one
    line that tells where the topics go (renamed, or onto the live robots), if any: a
    replay that never reaches it sent nothing anywhere, and says only why.

    Raises:
        FleetError: The file cannot be read, is not MCAP or holds no message to replay;
            the server refused the token (exit 3) or a topic (no send permission); the
            first connection failed (the server not reached, its certificate not
            trusted, ...); the link did not drain in time; no_drop messages were dropped.
        ConfigError: ``ca_file`` cannot be loaded.
    """
    recording_files(path)  # a bad path is said before anything connects
    line = replaytopics.notice(replaytopics.recorded_topics(path), options.remap,
                               options.onto_live_robots)
    config = ClientConfig(server_url=options.server_url, robot_name=options.robot_name,
                          token=options.token)
    link = RobotLink(config, on_frame=lambda _frame: None,
                     ssl_context=ca_context(options.ca_file))
    with _failures_reported_here(link):
        return await _replay_on(link, path, options, _ConnectedNotice(link, line, say))


@contextlib.contextmanager
def _failures_reported_here(link: RobotLink) -> Iterator[None]:
    """While replaying, the link's explanations of a refused token, and of a failed first
    connection, are not printed: the replay stops at once with its own one-line error
    (:func:`_check_refused`), where the link's would add a second, saying it keeps
    retrying. Nor are its warnings of refused topics: the replay's error names them all
    (:func:`_check_delivered`), where the link printed one line per topic above it."""
    link_log = logging.getLogger("fleetctl.client.link")
    reported = _DropReported(link)
    link_log.addFilter(reported)
    try:
        yield
    finally:
        link_log.removeFilter(reported)


class _DropReported(logging.Filter):
    """Drops the log records the link marks :data:`REFUSAL_RECORD` or
    :data:`REFUSED_TOPIC_RECORD`, and those it marks :data:`UNREACHABLE_RECORD` while it
    never connected (later outages are waited out, and their explanations are the user's
    only news of them)."""

    def __init__(self, link: RobotLink) -> None:
        super().__init__()
        self.link = link

    def filter(self, record: logging.LogRecord) -> bool:
        """``False`` for a refusal's explanation, or a first connection's failure."""
        if getattr(record, REFUSAL_RECORD, False) or getattr(record, REFUSED_TOPIC_RECORD,
                                                             False):
            return False
        return not (getattr(record, UNREACHABLE_RECORD, False)
                    and self.link.stats()["connects"] == 0)


class _ConnectedNotice:
    """The replay's line about where its topics go (``None``: nothing to say), said once
    the link first connected: a replay that never reaches the server sent nothing
    anywhere, and its error stays the one line that says why."""

    def __init__(self, link: RobotLink, line: str | None, say: Callable[[str], None]):
        self.link, self.line, self.say = link, line, say

    def said(self) -> bool:
        """Say the line if the link has connected; whether it is said (or was none)."""
        if self.line is not None and self.link.connects:
            self.say(self.line)
            self.line = None
        return self.line is None

    async def run(self) -> None:
        """Say it as soon as the link connects (the task is cancelled at the end)."""
        while not self.said():
            await asyncio.sleep(_DRAIN_POLL_S)  # polling the link's connection counter


async def _replay_on(link: RobotLink, path: Path, options: ReplayOptions,
                     notice: _ConnectedNotice) -> ReplayResult:
    """:func:`replay` with its *link* made; *notice* is said beside it."""
    runner = asyncio.create_task(link.run())
    announcing = asyncio.create_task(notice.run())
    result = ReplayResult(path)
    started = time.monotonic()
    corrupt: str | None = None
    try:
        try:
            await _play(path, options, link, result)
        except files.DamagedRecording as exc:
            corrupt = str(exc)  # what was read before the damage is still delivered
        if result.messages == 0 and corrupt is None:
            raise FleetError(_nothing_to_replay(path, result))
        if result.messages:
            await _drain(link, runner)
    finally:
        announcing.cancel()
        notice.said()  # a replay done between two polls connected too
        await link.stop()
        with contextlib.suppress(asyncio.CancelledError):
            await runner
        with contextlib.suppress(asyncio.CancelledError):
            await announcing
        result.duration_s = time.monotonic() - started
    _check_delivered(link, result, options)
    if corrupt is not None:
        done = (f"the {result.messages} message(s) before it were replayed"
                if result.messages else "nothing before it to replay")
        raise FleetError(f"{path}: damaged data, the rest of the file cannot be read "
                         f"({corrupt}); {done}")
    return result


def _nothing_to_replay(path: Path, result: ReplayResult) -> str:
    if result.skipped:
        types = ", ".join(sorted(t or "<no schema>" for t in result.skipped))
        return f"{path}: no message to replay: every type lacks a usable schema ({types})"
    return (f"{path}: no message to replay (an empty recording, or a file cut before its "
            "first complete chunk)")


def _check_refused(link: RobotLink) -> None:
    """A refused token is final for a replay (a robot would wait for the auth map to
    change; a person at a terminal wants to know now), and so is one refused for now
    (too many failed logins from this address: exit 7, with the server's wait), and a
    first connection that failed (the server is expected to be up; a robot would wait
    for it, a replay that waited 30 s said only "never connected")."""
    if link.login_throttle is not None:
        raise throttled_error(f"replay: {link.config.server_url}", link.login_throttle)
    failed = link.connect_error
    if failed is not None and link.stats()["connects"] == 0:  # stats(): only on failure
        url = link.config.server_url
        raise FleetError(f"replay: --server {url}: "
                         f"{why_unreachable(failed, url.partition(':')[0])}")
    close = link.last_close or ""
    if close.startswith(("4401", "4403")):
        raise FleetError(f"replay: the server {link.config.server_url} refused this "
                         f"identity: {close} (check --token-file)", exit_code=ExitCode.CONFIG)


def _check_delivered(link: RobotLink, result: ReplayResult, options: ReplayOptions) -> None:
    stats = link.stats()
    result.dropped = sum(int(n) for topic in stats["topics"].values()
                         for key, n in topic.items() if key.startswith("dropped_"))
    refused = stats["refused_topics"]
    if refused:
        raise FleetError(f"replay: the server refused {len(refused)} topic(s), no send "
                         f"permission for this identity: {', '.join(refused)} (give it send "
                         "rules, or --remap to topics it may send)")
    overflow = link.scheduler.no_drop_overflow
    if options.no_drop and overflow:
        raise FleetError(f"replay: {overflow} message(s) dropped: the link's no_drop queue "
                         "was full")


async def _play(path: Path, options: ReplayOptions, link: RobotLink,
                result: ReplayResult) -> None:
    decoder = _Decoder()
    bounds = link.scheduler.config
    high = int(bounds.no_drop_queue_messages * _QUEUE_HIGH_FRACTION)
    high_bytes = int(bounds.no_drop_queue_bytes * _QUEUE_HIGH_FRACTION)
    first_log: int | None = None
    t0 = 0.0
    for rec in _messages(path):
        if not decoder.usable(rec.type_name, rec.schema):
            result.skipped[rec.type_name] = result.skipped.get(rec.type_name, 0) + 1
            continue
        if first_log is None:
            # The clock starts with the first message: the time its schema took to load
            # (tens of ms on a busy host) was taken off the gap to the second one.
            first_log, t0 = rec.log_ns, time.monotonic()
        if options.rate is not None:
            delay = t0 + (rec.log_ns - first_log) / 1e9 / options.rate - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)  # pacing the replay, not synchronization
        if options.no_drop:
            await _wait_for_room(link, high, high_bytes)
        _check_refused(link)
        remote = replaytopics.sent_topic(rec.topic, options.remap, options.onto_live_robots)
        if remote != rec.topic and replaytopics.remapped(rec.topic, options.remap) is None:
            result.renamed[recorded_prefix(rec.topic)] = replay_prefix(rec.topic)
        frame = decoder.frame(rec, remote, options.no_drop)
        link.offer(remote, frame, priority=1.0, no_drop=options.no_drop)
        result.messages += 1
        result.topics[remote] = result.topics.get(remote, 0) + 1


async def _wait_for_room(link: RobotLink, high: int, high_bytes: int) -> None:
    """Wait while the no_drop messages held (queued or unacknowledged) fill half the
    FIFO's message or byte bound: past either bound the link would drop them. Fails
    when the link makes no progress for ``_DRAIN_TIMEOUT_S``."""
    held = link.scheduler.no_drop_held
    deadline = time.monotonic() + _DRAIN_TIMEOUT_S
    while held[0] >= high or held[1] >= high_bytes:
        _check_refused(link)
        if time.monotonic() > deadline:
            raise _stuck(link, held[0])
        await asyncio.sleep(_DRAIN_POLL_S)  # backpressure from the bounded FIFO
        now = link.scheduler.no_drop_held
        if now[0] < held[0]:
            deadline = time.monotonic() + _DRAIN_TIMEOUT_S  # progress: acks came back
        held = now


def _stuck(link: RobotLink, queued: int) -> FleetError:
    stats = link.stats()
    why = (f"last close: {stats['last_close']}" if stats["connects"] else
           "never connected")
    return FleetError(f"replay: {queued} message(s) still queued after "
                      f"{_DRAIN_TIMEOUT_S:.0f} s (server {link.config.server_url}, {why})",
                      exit_code=ExitCode.RUNTIME)


async def _drain(link: RobotLink, runner: asyncio.Task[None]) -> None:
    deadline = time.monotonic() + _DRAIN_TIMEOUT_S
    while True:
        _check_refused(link)
        stats = link.stats()
        if (stats["no_drop_queued"] == 0 and stats["no_drop_unacked"] == 0
                and stats["in_flight_frames"] == 0 and stats["connects"] > 0):
            return
        if runner.done():
            runner.result()  # the link's own failure, if any
            raise FleetError("replay: the link stopped before every message was sent")
        if time.monotonic() > deadline:
            raise _stuck(link, stats["no_drop_queued"])
        await asyncio.sleep(_DRAIN_POLL_S)  # polling the link's counters with a deadline


def _is_prefix(text: str) -> bool:
    """A topic prefix: a topic name (no trailing '/'), or '/' alone."""
    return text == "/" or TOPIC.fullmatch(text) is not None


def _parse_remap(values: list[str]) -> tuple[tuple[str, str], ...]:
    out = []
    for value in values:
        old, sep, new = value.partition("=")
        if not sep or not _is_prefix(old) or not _is_prefix(new):
            # '/husky1=/ghost 1' was taken: every topic sent was one no ROS name can be.
            raise ConfigError(f"--remap {value!r}: expected /old_prefix=/new_prefix, each a "
                              "ROS topic prefix (/a/b_c: letters, digits, '_')")
        out.append((old, new))
    return tuple(out)


def _result_text(result: ReplayResult) -> str:
    lines = [f"replayed {result.messages} messages from {result.file} in "
             f"{result.duration_s:.1f} s"]
    lines += [f"  {topic}: {n}" for topic, n in sorted(result.topics.items())]
    lines += [f"  skipped {n} {t or '<no schema>'} (no usable schema)"
              for t, n in sorted(result.skipped.items())]
    if result.dropped:
        lines.append(f"  dropped {result.dropped} stale message(s) (--latest-only)")
    return "\n".join(lines)


def register(app: typer.Typer) -> None:
    """Add the ``replay`` command to *app*."""

    @app.command("replay")
    def replay_command(
        file: Path = typer.Argument(..., help="The .mcap recording, or a rosbag2 bag "
                                    "directory (ros2 bag record -s mcap)."),
        server: str = typer.Option(..., "--server", "-s", help="ws:// or wss:// URL of the "
                                   "server: `fleetctl up`'s HTTPS port as wss://HOST:PORT/."),
        rate: float = typer.Option(1.0, "--rate", help="Speed: 1 real time, 2 twice as "
                                   "fast; 0: as fast as the link takes them."),
        token_file: Path | None = typer.Option(None, "--token-file",
                                               help="File holding the robot's token."),
        robot: str = typer.Option("replay", "--robot", help="Robot name (server session)."),
        remap: list[str] = typer.Option([], "--remap", help="Rename a topic prefix: "
                                        "/husky1=/ghost1 (repeatable)."),
        latest_only: bool = typer.Option(False, "--latest-only", help="Let the link drop "
                                         "stale messages per topic, as a live robot does."),
        ca_file: Path | None = typer.Option(None, "--ca-file", help="CA bundle to verify a "
                                            "wss:// server with (a fleet's own: "
                                            "FLEET/server/tls/cert.pem)."),
        onto_live_robots: bool = typer.Option(
            False, "--onto-live-robots", help="Send the recorded topic names (those no "
            "--remap renames), onto the robots online: they receive the recorded goals and "
            "commands. Without it every topic goes out under a name no live robot has, "
            "/husky1/scan as /husky1_replay/scan, said in one line."),
        output: OutputFormat = output_option(),
    ) -> None:
        """Play an MCAP recording into a fleet as a robot, live (real time or faster).

        By default no live robot receives it: /husky1/... goes out as
        /husky1_replay/... (a robot of its own on the page); --onto-live-robots sends
        the recorded names.
        """
        if not math.isfinite(rate) or rate < 0:
            raise ConfigError(f"--rate {rate}: must be a number >= 0")
        if not _ROBOT_NAME.fullmatch(robot):
            raise ConfigError(f"--robot {robot!r}: must match [A-Za-z][A-Za-z0-9_]* (at most "
                              "63 characters)")
        if not server.startswith(("ws://", "wss://")):
            raise ConfigError(f"--server {server!r}: expected a ws:// or wss:// URL")
        try:
            parse_uri(server)
        except (InvalidURI, ValueError) as exc:  # ValueError: urllib's bad IPv6 or port
            raise ConfigError(f"--server {server!r}: not a URL: {exc}") from None
        if ca_file is not None and not server.startswith("wss://"):
            raise ConfigError(f"--ca-file: verifies a wss:// server; {server} is plain ws:// "
                              "(no TLS)")
        options = ReplayOptions(server, rate or None, read_token_file(token_file), robot,
                                _parse_remap(remap), not latest_only, ca_file,
                                onto_live_robots)
        result = asyncio.run(replay(file, options, warn))
        emit(result, output, lambda: _result_text(result))
