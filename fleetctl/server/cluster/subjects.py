"""Topic -> NATS subject mapping and subscription interest (docs/scaling.md, "Subjects").

A ROS topic ``/robot1/cam/image`` becomes ``<prefix>.robot1.cam.image``: one subject token
per topic segment. NATS gives ``.`` (token separator), ``*`` and ``>`` (wildcards) and
white space a meaning, and an empty token is not a valid subject, so each segment is
escaped: ``A-Z a-z 0-9 _ -`` stay, every other byte of its UTF-8 form becomes ``~HH``
(upper-case hex; ``~`` itself is ``~7E``), and an empty segment becomes ``~``. A topic
that does not start with ``/`` gets the marker token ``~~`` after the prefix. The mapping
is one-to-one, so two topics never share a subject.

A subscription regex becomes the NATS subject that covers every topic it can match: its
literal topic, or the whole segments of its literal prefix followed by ``>``, or
``<prefix>.>`` when nothing simpler is safe. The relay still matches the full RE2 regex and
the receive rules on delivery, so a wide NATS subscription costs bandwidth, never
correctness.
"""

from __future__ import annotations

from collections.abc import Iterable

_PLAIN = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-")
EMPTY_TOKEN = "~"
RELATIVE_TOKEN = "~~"
# RE2 characters that end a literal prefix; after a quantifier the character before it is
# optional, so it leaves the prefix too.
_META = frozenset("\\.[](){}^$|")
_QUANTIFIERS = frozenset("*+?{")

# NATS refuses a control line (PUB <subject> <size>) past 4 KiB by default.
MAX_SUBJECT_BYTES = 3072
# Frames (and bytes) NATS may hold for one slow subscription of a replica before it drops
# (counted slow_consumer): the relay's own schedulers bound what each connection gets.
SUB_PENDING_MESSAGES = 65536
SUB_PENDING_BYTES = 64 * 1024 * 1024


def escape_token(segment: str) -> str:
    """One topic segment as a NATS subject token (never empty, no ``.``, ``*``, ``>``)."""
    if not segment:
        return EMPTY_TOKEN
    if all(c in _PLAIN for c in segment):
        return segment
    return "".join(c if c in _PLAIN else _hex(c) for c in segment)


def _hex(char: str) -> str:
    return "".join(f"~{b:02X}" for b in char.encode("utf-8", "surrogatepass"))


CONTROL_TOKEN = "~ctl"
"""Second token of the replicas' own control subjects. Escaping never makes it from a
topic segment (``~`` becomes ``~7E``), so control messages and frames never share a
subject; a wide topic subscription (``<prefix>.>``) still receives them, and the receiver
skips them (:func:`is_control_subject`)."""


def control_subject(prefix: str, name: str) -> str:
    """The subject of control message *name* between replicas (``keyframe``)."""
    return f"{prefix}.{CONTROL_TOKEN}.{name}"


def is_control_subject(prefix: str, subject: str) -> bool:
    return subject.startswith(f"{prefix}.{CONTROL_TOKEN}.")


def topic_subject(prefix: str, topic: str) -> str:
    """The subject frames on *topic* are published to."""
    if topic.startswith("/"):
        segments = topic[1:].split("/")
        return ".".join((prefix, *map(escape_token, segments)))
    return ".".join((prefix, RELATIVE_TOKEN, *map(escape_token, topic.split("/"))))


def pattern_subject(prefix: str, pattern: str, literal: str | None) -> str:
    """The subject a replica subscribes to for a local subscription *pattern*.

    Args:
        prefix: The cluster's subject prefix.
        pattern: The RE2 full-match pattern.
        literal: The pattern's topic when it has no metacharacters (``FullMatch.literal``).
    """
    if literal is not None:
        return topic_subject(prefix, literal)
    if "|" in pattern:  # an alternative may start anywhere: no common prefix
        return prefix + ".>"
    head, whole_pattern = literal_prefix(pattern)
    if whole_pattern:  # an escaped literal, e.g. the page's `/robot\.1/status`
        return topic_subject(prefix, head)
    if not head.startswith("/"):
        return prefix + ".>"
    return prefix_subject(prefix, head)


def prefix_subject(prefix: str, head: str) -> str:
    """The subject covering every topic that starts with *head*: its whole segments, then
    ``>`` (``<prefix>.>`` when it has none; a relative topic's segments follow
    :data:`RELATIVE_TOKEN`)."""
    if head.startswith("/"):
        tokens = head[1:].split("/")[:-1]  # the last segment may continue past the prefix
    elif "/" in head:
        tokens = head.split("/")[:-1]
        return ".".join((prefix, RELATIVE_TOKEN, *map(escape_token, tokens), ">"))
    else:
        return prefix + ".>"
    return ".".join((prefix, *map(escape_token, tokens), ">"))


def literal_prefix(pattern: str) -> tuple[str, bool]:
    """The characters every full match of *pattern* starts with, and whether that is the
    whole pattern (a literal written with escapes).

    Conservative: it stops at the first metacharacter; ``\\`` followed by a punctuation
    character is that character (RE2 syntax), any other escape (``\\d``, ``\\x41``)
    stops it.
    """
    out: list[str] = []
    i = 0
    while i < len(pattern):
        char = pattern[i]
        if char in _QUANTIFIERS:
            return "".join(out[:-1]), False
        if char == "\\" and i + 1 < len(pattern) and _escaped_literal(pattern[i + 1]):
            if i + 2 < len(pattern) and pattern[i + 2] in _QUANTIFIERS:
                return "".join(out), False
            out.append(pattern[i + 1])
            i += 2
            continue
        if char in _META:
            return "".join(out), False
        out.append(char)
        i += 1
    return "".join(out), True


def _escaped_literal(char: str) -> bool:
    return char.isascii() and not char.isalnum() and char.isprintable() and char != " "


def cover(subjects: Iterable[str]) -> frozenset[str]:
    """The *subjects* no wider ``X.>`` among them already covers.

    Subscribing to exactly these delivers each message once: NATS sends a message once
    per matching subscription, and no two of these match the same subject.
    """
    every = set(subjects)
    wild = {s[:-2] for s in every if s.endswith(".>")}
    return frozenset(s for s in every if not covered(s, wild))


def covered(subject: str, wild: set[str]) -> bool:
    """Whether some ``X.>`` with ``X`` in *wild* covers *subject* (literal, or itself
    ending in ``>``)."""
    tokens = subject.split(".")
    base = tokens[:-1] if tokens[-1] == ">" else tokens
    return any(".".join(base[:k]) in wild for k in range(1, len(base)))


def meet(a: str, b: str) -> str | None:
    """The subject covering the topics both *a* and *b* cover, each a topic's subject or
    ``X.>``; ``None`` if they share none. Two such subjects are nested or disjoint, so the
    narrower one is the answer."""
    if a == b:
        return a
    if a.endswith(".>") and covered(b, {a[:-2]}):
        return b
    if b.endswith(".>") and covered(a, {b[:-2]}):
        return a
    return None


def subject_matches(subject: str, pattern: str) -> bool:
    """Whether NATS subscription subject *pattern* (``*``, ``>``) matches *subject*."""
    tokens, wanted = subject.split("."), pattern.split(".")
    for i, want in enumerate(wanted):
        if want == ">":
            return len(tokens) > i
        if i >= len(tokens) or (want != "*" and want != tokens[i]):
            return False
    return len(tokens) == len(wanted)
