"""Subjects derived from regexes and narrowed by receive rules (no NATS needed)."""

from __future__ import annotations

import re

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from fleetctl.server.cluster.regexsubjects import (
    MAX_ALTERNATIVES,
    MAX_ALTERNATIVES_CHARS,
    narrowed_subjects,
    regex_subjects,
    split_alternatives,
)
from fleetctl.server.cluster.subjects import subject_matches, topic_subject
from fleetctl.server.regex import BadRegex, compile_full

P = "fleetctl"


def subjects(pattern: str) -> set[str]:
    return set(regex_subjects(P, pattern).subjects)


def narrowed(pattern: str, *receive: str) -> set[str]:
    return set(narrowed_subjects(P, pattern, receive).subjects)


@pytest.mark.parametrize(("pattern", "expected"), [
    ("/husky1/status", {"fleetctl.husky1.status"}),
    ("/husky1/.*", {"fleetctl.husky1.>"}),
    ("^/husky1/.*$", {"fleetctl.husky1.>"}),  # anchors
    ("\\A/husky1/.*\\z", {"fleetctl.husky1.>"}),
    ("(?:/husky1)/.*", {"fleetctl.husky1.>"}),  # a group before the first metacharacter
    ("[/]husky1/.*", {"fleetctl.husky1.>"}),  # a class of one
    ("(?:/husky1/status)", {"fleetctl.husky1.status"}),  # one topic only
    ("/robot\\.1/status", {"fleetctl.robot~2E1.status"}),  # escaped: the page's names
    ("/robot\\.1/.*", {"fleetctl.robot~2E1.>"}),
    ("/é/.*", {"fleetctl.~C3~A9.>"}),  # escaped token, multi-byte prefix
    ("/with space/.*", {"fleetctl.with~20space.>"}),
    ("relative/x/.*", {"fleetctl.~~.relative.x.>"}),
    ("/husky1.*", {"fleetctl.>"}),  # the segment may go on: /husky10/x
    ("/husky1(/.*)?", {"fleetctl.>"}),  # /husky1 itself and below: no common token
    ("/[^/]+/.*", {"fleetctl.>"}),  # every robot
    (".*", {"fleetctl.>"}),
    ("(?i)/husky1/.*", {"fleetctl.>"}),  # /HUSKY1/, and U+017F folds to s
    ("/husky1/.{70}", {"fleetctl.husky1.>"}),  # RE2 cannot bound it: the text's prefix
    # Alternations: split, each alternative bounded alone.
    ("(/husky1|/husky2)/.*", {"fleetctl.husky1.>", "fleetctl.husky2.>"}),
    ("/husky1/(goal_pose|initialpose)", {"fleetctl.husky1.goal_pose",
                                         "fleetctl.husky1.initialpose"}),
    ("/a/.*|/b/x", {"fleetctl.a.>", "fleetctl.b.x"}),
    ("/a/.*|/a/b/.*", {"fleetctl.a.>"}),  # covered by the wider one
    ("(?P<robot>/a|/b)/x", {"fleetctl.a.x", "fleetctl.b.x"}),
    ("/a/(?i:x|y)/z", {"fleetctl.a.>"}),  # flags scoped to the group: kept with it
    ("/a/(x|y)+/z", {"fleetctl.a.>"}),  # a repeated group is not distributed
    ("/a/[|(]/x", {"fleetctl.a.>"}),  # `|` and `(` in a class: not syntax, no split
    ("/a/\\|/x", {"fleetctl.a.~7C.x"}),  # an escaped `|`
    ("/a/x{(1|2)}", {"fleetctl.a.x~7B1~7D", "fleetctl.a.x~7B2~7D"}),  # literal braces
    ("/a/[]|]/(b|c)", {"fleetctl.a.>"}),  # `]` first in a class is a member
    ("/a/[[:alpha:]|]/(b|c)", {"fleetctl.a.>"}),
])
def test_subjects_of_regexes(pattern: str, expected: set[str]) -> None:
    assert subjects(pattern) == expected
    assert not regex_subjects(P, pattern).unclear


@pytest.mark.parametrize("pattern", [
    "(?i)/a/.*|/b/.*",  # (?i) reaches past `|`: `/B/x` matches
    "/b/.*|(?i)/a/.*",
    "\\Q/a|\\E/.*|/b/.*",  # quoted text: its `|` is not syntax
    "|".join(f"/r{i}/.*" for i in range(MAX_ALTERNATIVES + 1)),
    "(" + "|".join(f"/r{i}" for i in range(6)) + ")(" + "|".join("abcdef") + ")/.*",
    "(/a|/b)/" + "x" * (MAX_ALTERNATIVES_CHARS // 2),  # each copy of the rest counts
])
def test_unclear_alternations_are_bounded_whole(pattern: str) -> None:
    derived = regex_subjects(P, pattern)
    assert derived.unclear
    assert split_alternatives(pattern) is None
    assert derived.subjects == {"fleetctl.>"}


def test_flag_groups_that_reach_past_a_bar_are_never_split() -> None:
    # Split, `/B/x` would be left out, yet it matches.
    assert compile_full("(?i)/a/.*|/b/.*").matches("/B/x")
    assert split_alternatives("(?i)/a/.*|/b/.*") is None
    assert split_alternatives("/a/(?i)x|y") is None


@pytest.mark.parametrize(("pattern", "topic"), [
    ("(/a|/b){2}/.*", "/a/b/x"),  # as `(?:/a){2}` or `(?:/b){2}`: neither covers it
    ("((/a|/b)/c){2}", "/a/c/b/c"),  # repeated by an enclosing group
    ("(/a|/b)*/c/.*", "/b/a/c/x"),
])
def test_repeated_groups_are_not_distributed(pattern: str, topic: str) -> None:
    assert compile_full(pattern).matches(topic)
    assert split_alternatives(pattern) == [pattern]
    assert any(subject_matches(topic_subject(P, topic), s) for s in subjects(pattern))


def test_distributed_groups_keep_their_meaning() -> None:
    assert split_alternatives("(/a|/b)/.*") == ["(?:/a)/.*", "(?:/b)/.*"]
    assert split_alternatives("/a/(?i:x|y)") == ["/a/(?i:x)", "/a/(?i:y)"]
    assert split_alternatives("/a(/b|/c(/d|/e))") == [
        "/a(?:/b)", "/a(?:/c(?:/d))", "/a(?:/c(?:/e))"]
    assert split_alternatives("/a/b") == ["/a/b"]


@pytest.mark.parametrize(("pattern", "receive", "expected"), [
    # The page's broad subscription and a viewer token of one robot.
    (".*", ("/husky1/.*",), {"fleetctl.husky1.>"}),
    (".*", ("/husky1/.*", "/husky2/status"), {"fleetctl.husky1.>",
                                                "fleetctl.husky2.status"}),
    # A robot's own rules: its commands only.
    (".*", ("/husky1/(goal_pose|initialpose)",), {"fleetctl.husky1.goal_pose",
                                                   "fleetctl.husky1.initialpose"}),
    # A rule with no literal prefix keeps the subscription's own subjects.
    (".*", ("/husky1/.*", "/[^/]+/status"), {"fleetctl.>"}),
    ("/husky1/.*", (".*",), {"fleetctl.husky1.>"}),
    ("/husky.*", ("/husky1/cam/.*",), {"fleetctl.husky1.cam.>"}),
    ("/husky1/.*", ("/husky1/cam/.*", "/husky2/.*"), {"fleetctl.husky1.cam.>"}),
    # Nothing both allow: nothing to subscribe to.
    ("/husky2/.*", ("/husky1/.*",), set()),
    # An exact topic is as narrow as it gets.
    ("/husky1/status", ("/husky1/.*",), {"fleetctl.husky1.status"}),
])
def test_receive_rules_narrow_a_subscription(pattern: str, receive: tuple[str, ...],
                                             expected: set[str]) -> None:
    assert narrowed(pattern, *receive) == expected


def test_no_rules_known_keeps_the_subscriptions_subjects() -> None:
    assert narrowed_subjects(P, ".*", None).subjects == {"fleetctl.>"}


def test_an_unclear_rule_is_said() -> None:
    derived = narrowed_subjects(P, ".*", ("/husky1/.*", "(?i)/a/.*|/b/.*"))
    assert derived.unclear and derived.subjects == {"fleetctl.>"}
    assert not narrowed_subjects(P, ".*", ("/husky1/.*",)).unclear


# -- soundness: every topic a regex matches is covered -------------------------------

_ATOMS = ["/", "/", "/a", "/b", "a", "b", "A", "1", "\\.", ".", "[ab]", "[^/]", "[|/]", "é",
          "\\|", "(?i:a)", "(?i)", "[[:alpha:]]", "\\d"]


def _regexes() -> st.SearchStrategy[str]:
    atom = st.sampled_from(_ATOMS)

    def grow(inner: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
        quantified = st.tuples(inner, st.sampled_from(["", "", "?", "*", "+", "{2}", "{1,2}"])
                               ).map("".join)
        sequence = st.lists(quantified, min_size=1, max_size=4).map("".join)
        alternation = st.lists(sequence, min_size=1, max_size=3).map("|".join)
        return st.one_of(sequence, alternation.map(lambda a: f"({a})"),
                         alternation.map(lambda a: f"(?:{a})"))

    body = st.recursive(atom, grow, max_leaves=6)
    pieces = st.lists(body, min_size=1, max_size=3)
    return st.tuples(st.sampled_from(["", "", "^", "(?i)"]), pieces,
                     st.sampled_from(["", "|"])).map(
        lambda t: t[0] + t[2].join(t[1]))


def _topic_for(pattern: str) -> st.SearchStrategy[str]:
    """Topics the pattern matches (Python's regex syntax agrees with RE2's on the
    grammar above; a topic RE2 does not match is skipped), and others."""
    text = st.text(alphabet="/abA1.é|", max_size=8)
    python = pattern.replace("[[:alpha:]]", "[a-zA-Z]")
    try:
        re.compile(python)
    except re.error:  # e.g. (?i) after the start, which RE2 takes
        return text
    return st.one_of(st.from_regex(python, fullmatch=True), text)


_RULES = st.sampled_from(["/a/.*", "/b/.*", "(/a|/b)/.*", "/a/(a|b)", ".*", "/[^/]+/.*",
                          "(?i)/a/.*", "/a/b/.*", "/a/.*|/b/b", "^/a/.*$"])


def _covered(topic: str, found: frozenset[str]) -> bool:
    return any(subject_matches(topic_subject(P, topic), s) for s in found)


def _pattern_and_a_match(data: st.DataObject) -> tuple[str, str]:
    """A drawn regex that RE2 compiles and a topic it fully matches (others assumed away)."""
    pattern = data.draw(_regexes())
    try:
        compiled = compile_full(pattern)
    except BadRegex:
        assume(False)
        raise  # assume(False) does not return
    topic = data.draw(_topic_for(pattern))
    assume(compiled.matches(topic))
    return pattern, topic


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                   HealthCheck.filter_too_much])
@given(st.data())
def test_every_match_is_covered(data: st.DataObject) -> None:
    pattern, topic = _pattern_and_a_match(data)
    assert _covered(topic, regex_subjects(P, pattern).subjects), pattern


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.filter_too_much])
@given(st.data())
def test_every_receivable_match_is_covered_when_narrowed(data: st.DataObject) -> None:
    pattern, topic = _pattern_and_a_match(data)
    # Rules the topic may well match: the usual ones, its own first segment or itself.
    head = topic[: topic.find("/", 1) + 1] if topic.startswith("/") else ""
    rule = data.draw(st.one_of(_RULES, st.just(re.escape(head) + ".*"),
                               st.just(re.escape(topic)), _regexes()))
    try:
        allowed = compile_full(rule)
    except BadRegex:
        assume(False)
        return
    assume(allowed.matches(topic))
    found = narrowed_subjects(P, pattern, (rule, "/zz/.*")).subjects
    assert _covered(topic, found), (pattern, rule)
