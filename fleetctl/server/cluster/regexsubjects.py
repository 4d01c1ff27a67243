"""The NATS subjects that cover every topic a regex can match, as narrow as can be shown
(docs/scaling.md, "Interest narrowed by receive rules").

:func:`~fleetctl.server.cluster.subjects.pattern_subject` reads a literal prefix off the
pattern's text and gives up at the first alternation. Here a pattern is first split into
alternatives (``(/husky1|/husky2)/.*`` is ``/husky1/.*`` or ``/husky2/.*``;
``/husky1/(goal_pose|initialpose)`` two exact topics), then each alternative is bounded by
RE2 itself (:meth:`~fleetctl.server.regex.FullMatch.bounds`): every topic it matches lies
between two byte strings, so every one starts with their common prefix, whatever anchors,
escapes, classes or groups the text uses. The whole segments of that prefix become the
subject (``/husky1/`` -> ``<prefix>.husky1.>``); an alternative that can match one topic
only becomes that topic's subject.

Sound: the subjects always cover every topic the regex matches (they may cover more),
since the relay delivers only what a subject brings. Where a split is not certain to keep
the pattern's meaning (a flag group such as ``(?i)`` that reaches past ``|``,
``\\Q...\\E``, more than :data:`MAX_ALTERNATIVES` alternatives or
:data:`MAX_ALTERNATIVES_CHARS` of them, an alternative RE2 refuses), the pattern is
bounded whole (``(?i)/a/.*|/b/.*`` gives ``<prefix>.>``) and the answer says so
(``unclear``).
"""

from __future__ import annotations

import functools
import itertools
from typing import NamedTuple

from fleetctl.server.cluster.subjects import (
    cover,
    literal_prefix,
    meet,
    prefix_subject,
    topic_subject,
)
from fleetctl.server.regex import BadRegex, compile_full

# Why bounds: each alternative is one more RE2 compile and DFA walk on the event loop
# (0.2-0.4 ms here; 16 alternatives of 60 characters took 4.6 ms, once per pattern, then
# memoized) and one more subject; distributing a group copies the text around it into
# every alternative, so a client's 4 KiB subscription split 32 ways took 25 ms. Past
# either bound the pattern is bounded whole (a subscription's bounds are computed for its
# first frames anyway). A rule listing 200 robots' topics is better announced by its
# common prefix.
MAX_ALTERNATIVES = 16
MAX_ALTERNATIVES_CHARS = 1024
_QUANTIFIERS = frozenset("*+?{")
_FLAGS = frozenset("imsU-")


class Derived(NamedTuple):
    """What :func:`regex_subjects` found.

    Attributes:
        subjects: Subjects that together cover every topic the regex can match.
        unclear: The regex has alternatives that were not split (see the module's
            docstring): the subjects may be wider than a finer reading would give.
    """

    subjects: frozenset[str]
    unclear: bool


@functools.lru_cache(maxsize=4096)
def regex_subjects(prefix: str, pattern: str) -> Derived:
    """The subjects covering every topic that fully matches *pattern* (RE2, already
    known to compile).

    Args:
        prefix: The cluster's subject prefix.
        pattern: A subscription regex or a receive rule's regex.
    """
    alternatives = split_alternatives(pattern)
    unclear = alternatives is None
    subjects: set[str] = set()
    for alternative in alternatives or [pattern]:
        subjects.add(_alternative_subject(prefix, alternative))
    return Derived(cover(subjects), unclear)


def narrowed_subjects(prefix: str, pattern: str,
                      receive: tuple[str, ...] | None) -> Derived:
    """The subjects a replica needs for a subscription *pattern* held by a connection that
    may receive the topics of the *receive* regexes: only topics both cover can be
    delivered to it.

    Args:
        prefix: The cluster's subject prefix.
        pattern: The subscription regex (or literal topic).
        receive: The connection's receive rules' regexes; ``None``: not known (the
            subscription's own subjects).
    """
    own = regex_subjects(prefix, pattern)
    if receive is None or all(_is_exact(s) for s in own.subjects):
        return own  # an exact topic is as narrow as a subject gets
    rules = [regex_subjects(prefix, rule) for rule in receive]
    allowed = {s for rule in rules for s in rule.subjects}
    both = {m for s in own.subjects for r in allowed if (m := meet(s, r)) is not None}
    return Derived(cover(both), own.unclear or any(rule.unclear for rule in rules))


def _is_exact(subject: str) -> bool:
    return not subject.endswith(".>")


def _alternative_subject(prefix: str, alternative: str) -> str:
    """The narrowest subject shown to cover every full match of *alternative* (no
    ``|`` outside a group, or the whole pattern when it could not be split)."""
    head, whole = literal_prefix(alternative)
    if "|" in alternative:  # the text's prefix stops at nothing: an `|` may come first
        head, whole = "", False
    if whole:
        return topic_subject(prefix, head)
    try:
        bounds = compile_full(alternative).bounds()
    except BadRegex:  # the caller's pattern compiles; a split part might not (not kept)
        bounds = None
    if bounds is not None:
        low, high = bounds
        if low == high:  # every match lies between them: only this one topic
            topic = _decoded(low)
            if topic is not None:
                return topic_subject(prefix, topic)
        shared = _common_prefix(low, high)
        # Up to its last `/`: an ASCII byte, so what comes before it is whole UTF-8.
        common = _decoded(shared[: shared.rfind(b"/") + 1])
        if common is not None and len(common) > len(head) and common.startswith(head):
            head = common
    return prefix_subject(prefix, head)


def _common_prefix(a: bytes, b: bytes) -> bytes:
    """The bytes both start with: every byte string between the two starts with them."""
    n = next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y),
             min(len(a), len(b)))
    return a[:n]


def _decoded(raw: bytes) -> str | None:
    """*raw* as text, or ``None`` if it is not UTF-8 (a topic is)."""
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return None


# -- splitting alternatives ----------------------------------------------------------


class _Unclear(Exception):
    """The pattern uses syntax whose split is not certain to keep its meaning."""


def split_alternatives(pattern: str) -> list[str] | None:
    """*pattern* as alternatives whose full matches together are exactly its own: split
    at its top-level ``|``, and each group of alternatives not followed by a quantifier
    distributed (``a(b|c)d`` is ``a(?:b)d`` or ``a(?:c)d``); a pattern without ``|`` is
    itself.

    Returns:
        The alternatives, or ``None`` when a split could change what matches (a flag
        group without a colon, which RE2 applies past ``|`` to the end of its group;
        ``\\Q...\\E``; unbalanced text; more than :data:`MAX_ALTERNATIVES` or
        :data:`MAX_ALTERNATIVES_CHARS`; a part RE2 refuses).
    """
    if "|" not in pattern:
        return [pattern]
    if "\\Q" in pattern:  # quoted text: its `(`, `[` and `|` are not syntax
        return None
    done: list[str] = []
    todo = [pattern]
    try:
        while todo:
            expanded = _expand_once(todo.pop())
            if len(expanded) == 1:
                done.append(expanded[0])
            else:
                todo.extend(reversed(expanded))  # popped in the pattern's order
            if (len(done) + len(todo) > MAX_ALTERNATIVES
                    or sum(map(len, done)) + sum(map(len, todo)) > MAX_ALTERNATIVES_CHARS):
                return None
    except _Unclear:
        return None
    for alternative in done:
        try:
            compile_full(alternative)
        except BadRegex:
            return None
    return done


def _expand_once(pattern: str) -> list[str]:
    """One step: the pattern's top-level alternatives, else its first group of
    alternatives that no quantifier repeats (neither its own nor an enclosing group's:
    ``(a|b)*`` is not ``a*`` or ``b*``) distributed, else the pattern alone."""
    top_bars, groups = _structure(pattern)
    if top_bars:
        return _pieces(pattern, 0, len(pattern), top_bars)
    for group in groups:
        if group.bars and not group.repeated:
            # (?:...) keeps each alternative one unit: `a{(1|2)}` is `a{`, a digit, `}`,
            # and the bare `a{1}` would be a repeat.
            opener = group.opener if group.opener.endswith(":") else "(?:"
            before, after = pattern[: group.start], pattern[group.end + 1 :]
            return [f"{before}{opener}{alternative}){after}" for alternative
                    in _pieces(pattern, group.body, group.end, group.bars)]
    return [pattern]


def _pieces(pattern: str, start: int, end: int, bars: list[int]) -> list[str]:
    edges = [start - 1, *bars, end]
    return [pattern[a + 1 : b] for a, b in itertools.pairwise(edges)]


class _Group(NamedTuple):
    """A group: ``pattern[start:body]`` opens it, ``pattern[end]`` is its ``)``, *bars*
    are the ``|`` of its own level; *repeated*: a quantifier follows it or a group
    around it."""

    start: int
    body: int
    end: int
    opener: str
    bars: list[int]
    repeated: bool


def _structure(pattern: str) -> tuple[list[int], list[_Group]]:
    """The ``|`` outside every group, and the groups (in the order they open), of an RE2
    pattern.

    Raises:
        _Unclear: A flag group without a colon, or text that does not balance.
    """
    top_bars: list[int] = []
    closed: list[tuple[int, int, int, str, list[int]]] = []
    open_groups: list[tuple[int, int, str, list[int]]] = []
    i = 0
    while i < len(pattern):
        char = pattern[i]
        if char == "\\":
            i += 2  # the escaped character, whatever it is, is not syntax here
        elif char == "[":
            i = _class_end(pattern, i)
        elif char == "(":
            body = _body_start(pattern, i)
            open_groups.append((i, body, pattern[i:body], []))
            i = body
        elif char == ")":
            if not open_groups:
                raise _Unclear
            start, body, opener, bars = open_groups.pop()
            closed.append((start, body, i, opener, bars))
            i += 1
        else:
            if char == "|":
                (open_groups[-1][3] if open_groups else top_bars).append(i)
            i += 1
    if open_groups:
        raise _Unclear
    closed.sort()
    repeats = [(start, end) for start, _, end, _, _ in closed
               if pattern[end + 1 : end + 2] in _QUANTIFIERS]
    return top_bars, [
        _Group(start, body, end, opener, bars,
               any(a <= start and end <= b for a, b in repeats))
        for start, body, end, opener, bars in closed]


def _body_start(pattern: str, i: int) -> int:
    """Where the group opened at ``pattern[i]`` starts: after ``(``, ``(?:``,
    ``(?P<name>``, ``(?<name>`` or ``(?flags:``.

    Raises:
        _Unclear: ``(?flags)``, which reaches past ``|`` (or anything else after ``(?``).
    """
    if pattern[i + 1 : i + 2] != "?":
        return i + 1
    if pattern.startswith(("(?P<", "(?<"), i):
        close = pattern.find(">", i)
        if close < 0:
            raise _Unclear
        return close + 1
    j = i + 2
    while j < len(pattern) and pattern[j] in _FLAGS:
        j += 1
    if pattern[j : j + 1] != ":":
        raise _Unclear
    return j + 1


def _class_end(pattern: str, i: int) -> int:
    """The index after the ``]`` closing the class opened at ``pattern[i]`` (a ``]`` first
    in it is a member; ``[:alpha:]`` is one member; ``\\`` escapes).

    Raises:
        _Unclear: The class does not close.
    """
    j = i + 1
    if pattern[j : j + 1] == "^":
        j += 1
    if pattern[j : j + 1] == "]":
        j += 1
    while j < len(pattern):
        char = pattern[j]
        if char == "\\":
            j += 2
        elif pattern.startswith("[:", j):
            close = pattern.find(":]", j + 2)
            if close < 0:
                raise _Unclear
            j = close + 2
        elif char == "]":
            return j + 1
        else:
            j += 1
    raise _Unclear
