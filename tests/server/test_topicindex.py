"""The stored-topic index (fleetctl.server.topicindex) and the pattern bounds it relies on
(FullMatch.bounds): every topic a pattern matches is among its candidates, in order."""

from __future__ import annotations

import random

import pytest

from fleetctl.server.regex import FullMatch, compile_full
from fleetctl.server.topicindex import TopicIndex, topic_key

# Pieces of random patterns: literals (ASCII, non-ASCII, case), classes, groups,
# alternations, repetition, case folding and anchors, as subscriptions use them and more.
_ATOMS = ["/", "a", "b", "r", "7", "_", "é", "Z", "ü", ".", "[a-c]", "[^/]", "[/7]",
          r"\d", r"\w", r"\pL", r"\C", "(a|b)", "(/r|/a/)", "(?i:a)", "(?i:é)", "\\/"]
_QUANTIFIERS = ["", "", "", "*", "+", "?", "{1,3}", "{2}", "*?"]
_ALPHABET = ["/", "a", "b", "r", "7", "_", "é", "Z", "ü", "A", "É", "\U0001f916", "\x00", "x"]


def random_pattern(rng: random.Random) -> str:
    """A random RE2 pattern made of the pieces above (sometimes two alternatives)."""
    def branch() -> str:
        head = rng.choice(["", "", "(?i)", "^", "/r7/", "/a"])
        body = "".join(rng.choice(_ATOMS) + rng.choice(_QUANTIFIERS)
                       for _ in range(rng.randint(0, 5)))
        return head + body + rng.choice(["", "", "$", r"\b", ".*"])
    pattern = branch()
    return pattern + "|" + branch() if rng.random() < 0.2 else pattern


def random_topic(rng: random.Random) -> str:
    prefix = rng.choice(["", "/r7/", "/a", "/r", "/A"])
    return prefix + "".join(rng.choice(_ALPHABET) for _ in range(rng.randint(0, 7)))


def test_bounds_hold_every_topic_a_pattern_matches() -> None:
    """RE2's PossibleMatchRange, as used: a matched topic is never outside the bounds."""
    rng = random.Random(11)
    topics = [random_topic(rng) for _ in range(400)]
    bounded = 0
    for _ in range(600):
        pattern = FullMatch(random_pattern(rng))
        bounds = pattern.bounds()
        bounded += bounds is not None
        for topic in topics:
            if bounds is not None and pattern.matches(topic):  # (None: all may match)
                assert bounds[0] <= topic_key(topic) <= bounds[1], (pattern, topic, bounds)
    assert bounded > 300  # most patterns are bounded, or the index would not help


@pytest.mark.parametrize("binding", [True, False], ids=["binding-match", "public-fallback"])
def test_matches_answers_as_re2_fullmatch(binding: bool, monkeypatch: pytest.MonkeyPatch,
                                          ) -> None:
    """FullMatch and AnyOf ask the binding's Match directly: the same answers as
    google-re2's own fullmatch, a lone surrogate included (no match). A google-re2
    without those private names (``re2._Anchor``) gets the same answers by fullmatch."""
    import re2

    from fleetctl.server import regex
    from fleetctl.server.regex import AnyOf

    if not binding:
        monkeypatch.setattr(regex, "_ANCHOR_BOTH", None)
    assert (regex.full_matcher(re2.compile("a")).func is regex._full_match) == binding

    rng = random.Random(17)
    topics = [random_topic(rng) for _ in range(150)] + ["/r7/\ud800x", ""]
    patterns = [random_pattern(rng) for _ in range(150)]
    for text in patterns:
        pattern, reference = FullMatch(text), re2.compile(text)
        for topic in topics:
            try:
                want = reference.fullmatch(topic) is not None
            except UnicodeEncodeError:
                want = False
            assert pattern.matches(topic) == want, (text, topic)
    for _ in range(30):
        group = [compile_full(rng.choice(patterns)) for _ in range(rng.randint(2, 6))]
        joined = AnyOf(group)
        for topic in topics:
            assert joined.matches(topic) == any(p.matches(topic) for p in group)


@pytest.mark.parametrize(("pattern", "inside", "outside"), [
    ("/robot7/.*", "/robot7/scan", "/robot8/scan"),
    ("/robot7/scan", "/robot7/scan", "/robot7/scans"),
    ("(?i)/Robot7/.*", "/ROBOT7/x", "/robot8/x"),
    ("/a/x|/b/y", "/b/y", "/c/y"),
])
def test_bounds_of_usual_patterns(pattern: str, inside: str, outside: str) -> None:
    bounds = FullMatch(pattern).bounds()
    assert bounds is not None
    assert bounds[0] <= topic_key(inside) <= bounds[1]
    assert not bounds[0] <= topic_key(outside) <= bounds[1]


def test_patterns_re2_cannot_bound_have_none() -> None:
    assert FullMatch(".*").bounds() in (None, (b"", b"\xf4\xbf\xbf\xc0"))
    assert FullMatch(".*scan").bounds() is None or FullMatch(".*scan").bounds() == (
        b"\x00", b"\xf4\xbf\xbf\xc0")


def test_order_is_insertion_order_and_adding_again_moves_last() -> None:
    index = TopicIndex()
    for topic in ("/b", "/a", "/c"):
        index.add(topic)
    index.add("/b")
    assert list(index) == ["/a", "/c", "/b"] and len(index) == 3 and "/c" in index
    assert index.oldest() == "/a"
    index.discard("/c")
    index.discard("/nothing")
    assert list(index) == ["/a", "/b"] and "/c" not in index
    assert index.candidates([compile_full(".*")]) == ["/a", "/b"]


def test_candidates_of_a_prefix_pattern_are_its_range_only() -> None:
    index = TopicIndex()
    for i in range(4096):
        index.add(f"/r{i // 32}/t{i}")
    index.add("/r7/t230")  # moved last: candidates follow the index's order
    found = index.candidates([compile_full("/r7/.*")])
    assert found == [f"/r7/t{i}" for i in range(224, 256) if i != 230] + ["/r7/t230"]
    assert index.candidates([compile_full("/r7/t230")]) == ["/r7/t230"]
    assert index.candidates([compile_full("/r7/none")]) == []
    assert len(index.candidates([compile_full(".*scan")])) == 4096  # unbounded: all


def test_candidates_hold_every_match_in_order_under_churn() -> None:
    """Against a plain ordered dict and a scan of every topic."""
    rng = random.Random(5)
    index = TopicIndex()
    reference: dict[str, None] = {}
    patterns = [compile_full(random_pattern(rng)) for _ in range(40)]
    for step in range(1200):
        topic = random_topic(rng)
        if rng.random() < 0.6:
            reference.pop(topic, None)
            reference[topic] = None
            index.add(topic)
        else:
            reference.pop(topic, None)
            index.discard(topic)
        if step % 100 == 99:
            assert list(index) == list(reference)
            for pattern in patterns:
                candidates = index.candidates([pattern])
                assert len(set(candidates)) == len(candidates)
                assert [t for t in candidates if pattern.matches(t)] == [
                    t for t in reference if pattern.matches(t)], pattern
            for _ in range(20):  # several at once (a resumed session's patterns)
                group = rng.sample(patterns, rng.randint(2, 4))
                candidates = index.candidates(group)
                assert len(set(candidates)) == len(candidates)
                assert [t for t in candidates if any(p.matches(t) for p in group)] == [
                    t for t in reference if any(p.matches(t) for p in group)], group
