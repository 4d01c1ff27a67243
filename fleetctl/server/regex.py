"""RE2 full-match regexes, compiled once (MISSION: linear time, full match everywhere).

google-re2 logs parse errors to stderr through absl by default; we turn that off and turn
errors into :class:`BadRegex` with a readable message instead.
"""

from __future__ import annotations

import functools
import re as std_re
from collections.abc import Callable, Iterable
from typing import Any

import re2

# Why a memory budget: RE2's default (8 MiB per regex, for the program and the DFA cache
# that fills as it matches) let a 21-character subscription (".{1000}.{1000}.{1000}") cost
# the relay 0.8 MB and 11-20 ms of compiling on the event loop; 250 distinct ones from one
# token grew the relay by 100 MB. Topic patterns need a few KiB (a 4 KiB alternation of
# 200 robots' topics: 1,230 instructions); past the budget RE2 refuses the pattern
# ("pattern too large"), and a DFA out of budget falls back to the NFA (still linear).
MAX_REGEX_MEMORY_BYTES = 256 * 1024
# What a pattern costs in the subscription quotas (docs/security.md): its UTF-8 bytes, or
# this many per instruction of its compiled program when that is more, so that a short
# pattern with a large program cannot be held thousands of times within the byte quotas.
QUOTA_BYTES_PER_INSTRUCTION = 4

# How matches() asks RE2: the binding's own Match on the topic's UTF-8 bytes, anchored at
# both ends. Why not re2's fullmatch(): it wraps that call in a generator that maps byte
# offsets back to str offsets and builds a match object, 1.5-3.6 us a call here against
# 0.8 us for the yes/no answer wanted (a new ".*/x" subscription looks at 4,096 stored
# topics, the receiver cache asks every connection about a new topic). Those names are
# the binding's, not its documented API: where a google-re2 release lacks them, matches()
# falls back to fullmatch() (same answers, the old cost) instead of failing at import.
_ANCHOR_BOTH: Any = getattr(getattr(re2, "_Anchor", None), "ANCHOR_BOTH", None)
_NO_MATCH = (-1, -1)

_OPTIONS = re2.Options()
_OPTIONS.log_errors = False
_OPTIONS.max_mem = MAX_REGEX_MEMORY_BYTES

# Why a ceiling: a client chooses subscription regexes, and each compiled RE2 program costs
# memory; 4 KiB is far more than any topic pattern needs.
MAX_PATTERN_CHARS = 4096

# Bytes of a topic RE2 looks at when bounding what a pattern can match (FullMatch.bounds).
# Why 64: longer than the part of ROS topic names that tells them apart in the usual
# prefix patterns (`/robot7/camera/...`); a longer topic is still bounded (RE2 rounds the
# upper bound up), only less tightly.
BOUNDS_MAX_BYTES = 64

# Characters of ROS topic names that are never RE2 metacharacters: a pattern made only of
# these is a literal topic and is compared with ==, which is ~50x cheaper than RE2.
_LITERAL = std_re.compile(r"[A-Za-z0-9_/~-]*")


def _full_match(match: Any, anchor: Any, topic: str) -> bool:
    """Whether the RE2 program whose binding ``Match`` is *match* matches all of *topic*
    (*anchor*: the binding's ANCHOR_BOTH)."""
    try:
        encoded = topic.encode("utf-8")
    except UnicodeEncodeError:  # a lone surrogate: no UTF-8 topic, so none it could be
        return False
    return bool(match(anchor, encoded, 0, len(encoded))[0] != _NO_MATCH)


def _public_full_match(compiled: Any, topic: str) -> bool:
    """The same answer through re2's documented ``fullmatch`` (slower, see above)."""
    try:
        return compiled.fullmatch(topic) is not None
    except UnicodeEncodeError:  # a lone surrogate: no UTF-8 topic, so none it could be
        return False


def full_matcher(compiled: Any) -> Callable[[str], bool]:
    """Whether a topic matches *compiled* (an ``re2.compile`` result) from its first to
    its last character: through the binding's ``Match`` where this google-re2 has it,
    else through ``fullmatch``."""
    match = getattr(getattr(compiled, "_regexp", None), "Match", None)
    if _ANCHOR_BOTH is None or match is None:
        return functools.partial(_public_full_match, compiled)
    return functools.partial(_full_match, match, _ANCHOR_BOTH)


class BadRegex(ValueError):
    """A pattern RE2 cannot compile; ``str(exc)`` says why."""


class FullMatch:
    """A compiled RE2 pattern that answers "does it match the whole topic?".

    Attributes:
        pattern: The source text.
        literal: The topic itself when the pattern has no metacharacters, else ``None``
            (lets callers check a literal topic without running the regex; a literal is
            not compiled).
        cost: Bytes the pattern counts for in the subscription quotas: its UTF-8 bytes,
            or :data:`QUOTA_BYTES_PER_INSTRUCTION` per instruction of its RE2 program
            when that is more.
    """

    __slots__ = ("_bounds", "_bounds_known", "_match", "_regex", "cost", "literal", "pattern")

    def __init__(self, pattern: str) -> None:
        if len(pattern) > MAX_PATTERN_CHARS:
            raise BadRegex(f"pattern longer than {MAX_PATTERN_CHARS} characters")
        self.pattern = pattern
        self.literal = pattern if _LITERAL.fullmatch(pattern) else None
        self.cost = len(pattern.encode("utf-8", "surrogatepass"))
        self._bounds: tuple[bytes, bytes] | None = None
        self._bounds_known = False  # bounds() computes them once, when first asked
        if self.literal is not None:  # compared with ==: no program to build or keep
            self._regex: Any = None
            self._match: Any = None
            return
        try:
            self._regex = re2.compile(pattern, options=_OPTIONS)
        except re2.error as exc:
            detail = exc.args[0] if exc.args else "invalid"
            if isinstance(detail, bytes):
                detail = detail.decode("utf-8", "replace")
            raise BadRegex(str(detail)) from None
        except UnicodeEncodeError:  # a lone surrogate ("\ud800" in YAML or JSON): RE2 takes UTF-8
            raise BadRegex("not UTF-8 text (a lone surrogate code point)") from None
        self.cost = max(self.cost, QUOTA_BYTES_PER_INSTRUCTION * self._regex.programsize)
        self._match = full_matcher(self._regex)

    def matches(self, topic: str) -> bool:
        """Return whether *topic* matches the pattern from its first to its last character."""
        if self.literal is not None:
            return topic == self.literal
        return bool(self._match(topic))

    def bounds(self) -> tuple[bytes, bytes] | None:
        """The smallest and largest UTF-8 topic (bytes order) the pattern can match.

        Every topic it matches, encoded as UTF-8, lies between the two, both included
        (RE2's ``PossibleMatchRange``: it walks the pattern's DFA, so it holds for
        alternations, classes and case folding; RE2 rounds the upper bound up past
        :data:`BOUNDS_MAX_BYTES`). Why: a pattern such as ``/robot7/.*`` can then be
        matched against the few stored topics between ``/robot7/`` and its upper bound
        instead of against every one (:class:`~fleetctl.server.topicindex.TopicIndex`).
        Computed once, a few microseconds.

        Returns:
            ``(low, high)``, or ``None`` when RE2 cannot bound it (``.*`` and patterns
            starting with it, a DFA over its memory budget): any topic may match.
        """
        if not self._bounds_known:  # lazily: RE2 builds a DFA for it (memory)
            self._bounds = self._possible_range()
            self._bounds_known = True
        return self._bounds

    def _possible_range(self) -> tuple[bytes, bytes] | None:
        if self.literal is not None:
            literal = self.literal.encode("utf-8")
            return literal, literal
        try:
            ok, low, high = self._regex._regexp.PossibleMatchRange(BOUNDS_MAX_BYTES)
        except AttributeError:  # a binding without it: no bound, every topic a candidate
            return None
        if not ok or high < low:  # (RE2 says "no maximum" with ok = False)
            return None
        return bytes(low), bytes(high)

    def __repr__(self) -> str:
        return f"FullMatch({self.pattern!r})"


@functools.lru_cache(maxsize=4096)
def compile_full(pattern: str) -> FullMatch:
    """Compile *pattern* (cached: the same pattern text is compiled once per process).

    Raises:
        BadRegex: RE2 rejects the pattern.
    """
    return FullMatch(pattern)


# A connection's patterns joined into one alternation (AnyOf) may use more memory than
# one pattern; past this RE2 refuses the join and each pattern is tried in turn.
MAX_JOINED_MEMORY_BYTES = 1024 * 1024
_JOINED_OPTIONS = re2.Options()
_JOINED_OPTIONS.log_errors = False
_JOINED_OPTIONS.max_mem = MAX_JOINED_MEMORY_BYTES


class AnyOf:
    """Whether any of several full-match patterns matches a topic, in one RE2 call.

    Why: google-re2's Python binding costs 6-10 us per call whatever the pattern, and a
    topic the relay has not routed yet is checked against every subscription of every
    connection: 2,400 pattern subscriptions made each new topic cost 17-52 ms. Literal
    topics are looked up in a set; the regexes are joined into one alternation
    ``(?:p1)|(?:p2)|...`` (RE2 scopes flags such as ``(?i)`` to their group); a join RE2
    refuses (too large, or a pattern whose text cannot be wrapped, such as an open
    ``\\Q``) falls back to one call per pattern. Same answers as the patterns' own
    :meth:`FullMatch.matches`.
    """

    __slots__ = ("_each", "_joined", "_literals")

    def __init__(self, patterns: Iterable[FullMatch]) -> None:
        patterns = list(patterns)
        self._literals: frozenset[str] = frozenset(
            p.literal for p in patterns if p.literal is not None)
        regexes = [p for p in patterns if p.literal is None]
        self._joined: Any = None
        self._each: tuple[FullMatch, ...] = ()
        if len(regexes) == 1:
            self._each = (regexes[0],)
        elif regexes:
            text = "|".join(f"(?:{p.pattern})" for p in regexes)
            try:
                self._joined = full_matcher(re2.compile(text, options=_JOINED_OPTIONS))
            except (re2.error, UnicodeEncodeError):
                self._each = tuple(regexes)

    def matches(self, topic: str) -> bool:
        """Whether any of the patterns matches *topic* from its first to last character."""
        if topic in self._literals:
            return True
        joined = self._joined
        if joined is not None:
            return bool(joined(topic))
        return any(p.matches(topic) for p in self._each)
