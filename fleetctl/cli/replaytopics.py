"""Where ``fleetctl replay`` sends each recorded topic: the ``--remap`` the user gave, else
a name no live robot has (:mod:`fleetctl.deploy.replaynames`), unless
``--onto-live-robots``; and the one line that says so before anything is sent.

Why every first segment, not only the fleet's robots: the replay cannot know them. The
server's ``/robots`` lists the robots its registry has *seen* (not one never connected
since, nor one added while the replay runs; a removed one stays), and the ``welcome``
frame carries the token's rules, not the fleet. A topic of one segment (``/tf``) is
renamed too: a robot may subscribe to any topic (client.yaml's ``subscribe``).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from fleetctl.cli.replayfiles import recording_files
from fleetctl.deploy.replaynames import recorded_prefix, replay_prefix
from fleetctl.server.recording import files

Remap = tuple[tuple[str, str], ...]


def remapped(topic: str, remap: Remap) -> str | None:
    """*topic* renamed by the first ``(old_prefix, new_prefix)`` of *remap* that matches
    it, or ``None`` when none does."""
    for old, new in remap:
        if topic == old or topic.startswith(old.rstrip("/") + "/"):
            return new.rstrip("/") + topic[len(old.rstrip("/")):]
    return None


def sent_topic(topic: str, remap: Remap, onto_live_robots: bool) -> str:
    """The topic a recorded *topic* goes out as."""
    explicit = remapped(topic, remap)
    if explicit is not None:
        return explicit
    if onto_live_robots:
        return topic
    return replay_prefix(topic) + topic[len(recorded_prefix(topic)):]


def renames(topics: Iterable[str], remap: Remap) -> dict[str, str]:
    """``{recorded_prefix: replay_prefix}`` of the *topics* no ``--remap`` matches."""
    return {recorded_prefix(t): replay_prefix(t) for t in sorted(topics)
            if remapped(t, remap) is None}


def recorded_topics(path: Path) -> set[str]:
    """The topics of the recording *path* (a file, or a bag directory's files): from a
    complete file's summary, else by reading it (a damaged file: the topics before the
    damage; the replay says what the damage is)."""
    topics: set[str] = set()
    for recording in recording_files(path):
        try:
            topics.update(files.describe(recording)["topics"])
        except files.DamagedRecording:
            topics.update(_topics_before_damage(recording))
    return topics


def _topics_before_damage(recording: Path) -> set[str]:
    topics: set[str] = set()
    try:
        for _schema, channel, _message in files.read_messages(recording):
            topics.add(channel.topic)
    except files.DamagedRecording:
        pass
    return topics


def notice(topics: set[str], remap: Remap, onto_live_robots: bool) -> str | None:
    """The one line said before a replay of *topics* starts, or ``None`` (every topic
    has its ``--remap``)."""
    if onto_live_robots:
        live = sorted({recorded_prefix(t) for t in topics if remapped(t, remap) is None})
        if not live:
            return None
        return (f"replay: --onto-live-robots: sending under the recorded names "
                f"({', '.join(live)}): a robot online that subscribes to one of them (its "
                "goals, commands) receives and acts on it, and viewers see its live data "
                "mixed with the replayed")
    renamed = renames(topics, remap)
    if not renamed:
        return None
    mapping = ", ".join(f"{old} -> {new}" for old, new in renamed.items())
    return (f"replay: topics renamed so that no live robot receives them: {mapping} "
            "(--remap OLD=NEW to choose the names, --onto-live-robots to send the recorded "
            "ones)")
